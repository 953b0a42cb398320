"""The core and the simulator stand alone: numpy and scipy only, none of the I/O or ROS libraries.

A child interpreter is started with a meta-path blocker that makes ``rclpy``, ``yaml``,
``matplotlib`` and ``rosbags`` unimportable; in it, paper case 3.2 is simulated
(:mod:`mpm_monitor.sim`) and analysed (:mod:`mpm_monitor.core`).  The child also checks that no
module of the package outside ``core`` and ``sim`` was loaded on the way.
"""

import json
import subprocess
import sys
import textwrap

BLOCKED = ("rclpy", "yaml", "matplotlib", "rosbags")

CHILD = textwrap.dedent('''
    import importlib.abc
    import json
    import sys

    BLOCKED = {blocked!r}

    class Blocker(importlib.abc.MetaPathFinder):
        def find_spec(self, fullname, path=None, target=None):
            if fullname.split(".")[0] in BLOCKED:
                raise ImportError(f"{{fullname}} is blocked: the core and the simulator must not need it")
            return None

    sys.meta_path.insert(0, Blocker())
    for name in BLOCKED:
        try:
            __import__(name)
        except ImportError:
            pass
        else:
            raise SystemExit(f"the blocker let {{name}} through")

    import mpm_monitor
    mpm_monitor.limit_blas_threads()
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze
    from mpm_monitor.sim.cases import paper_case
    from mpm_monitor.sim.closed_loop import run_closed_loop

    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 3000, seed=1, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    report = analyze(case.model, log.as_logged_data("paper case 3.2"), AnalysisOptions())
    print(json.dumps({{
        "rows": sorted(report.flagged_rows), "elements": sorted(report.located_elements),
        "expected_rows": sorted(case.mismatched_rows), "expected_elements": sorted(case.mismatched_elements),
        "outside": sorted(m for m in sys.modules if m.startswith("mpm_monitor.")
                          and m.split(".")[1] not in ("core", "sim")),
        "blocked_loaded": sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)}}))
''').format(blocked=BLOCKED)


def test_core_and_sim_analyse_a_paper_case_without_ros_yaml_matplotlib_or_rosbags():
    proc = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["outside"] == [], f"modules outside core and sim were loaded: {got['outside']}"
    assert got["blocked_loaded"] == []
    assert got["rows"] == got["expected_rows"] == ["y1", "y2"]
    assert got["elements"] == got["expected_elements"]
