"""A ROS user's workspace: a clean copy of the package built by colcon, run from the install space.

What a ROS user does (README, "Use in a ROS 2 workspace"): put the package in ``<ws>/src``, run
``colcon build`` in ``<ws>``, source ``install/setup.bash`` and start the executables with
``ros2 run mpm_monitor <executable>``.  The ``ros2`` command itself is not installable here, so this
test does what it does: ``ros2 run`` takes the package prefix from the ament index
(``ament_index_python.packages.get_package_prefix``, which searches ``AMENT_PREFIX_PATH``) and
runs ``<prefix>/lib/<package>/<executable>``, a file with the executable bit.

The workspace is built once for the module, from the files a clone would have (``git ls-files``,
plus files not yet committed; no ``.venv``, no egg-info, no build artefacts), with the colcon
pinned in ``requirements.txt``, without ``--symlink-install`` (a real install).  The environment of
every process started from the install is the one ``source install/setup.bash`` gives.
"""

import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("colcon_core")
pytestmark = pytest.mark.timeout(300)

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from ros_domains import close_listener, domain_context, stop_process, unique_domain  # noqa: E402

from mpm_monitor.core.model import PlantModel  # noqa: E402
from mpm_monitor.io.model_file import save_model  # noqa: E402
from mpm_monitor.monitor.statuses import SUMMARY_NAME  # noqa: E402
from mpm_monitor.nodes.ros_io import VectorCodec, diagnostics_qos, make_executor, spin_until, vector_qos  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = "mpm_monitor"
NODES = ("plant_node", "mpc_node", "setpoint_node", "monitor_node", "recorder_node", "replay_node")
LAUNCHERS = ("suite_inprocess", "suite_processes", "monitor_only")
EXECUTABLES = NODES + LAUNCHERS + ("mpm_analyze",)
#: Left out of the copy even when present and not ignored by git.
NOT_COPIED = {".git", ".venv", "build", "install", "log", "__pycache__", ".pytest_cache", ".hypothesis"}


def clean_copy(dest: Path) -> None:
    """The package's files as a fresh clone has them (tracked or new, not ignored) copied to ``dest``."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                                cwd=ROOT, capture_output=True, check=True).stdout.decode().split("\0")
    except (OSError, subprocess.CalledProcessError):  # not a git checkout: copy the tree less the artefacts
        shutil.copytree(ROOT, dest, ignore=shutil.ignore_patterns(*NOT_COPIED, "*.egg-info"))
        return
    for rel in filter(None, listed):
        src = ROOT / rel
        if src.is_file() and not NOT_COPIED.intersection(Path(rel).parts):
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)


def sourced_env(setup_bash: Path) -> dict:
    """The environment after ``source <setup_bash>`` in bash (the one ``ros2 run`` would run in)."""
    out = subprocess.run(["bash", "-c", f'source "{setup_bash}" && env -0'], capture_output=True, check=True,
                         timeout=60).stdout.decode()
    return dict(item.split("=", 1) for item in out.split("\0") if "=" in item)


def ros2_run_path(env: dict, executable: str) -> Path:
    """What ``ros2 run mpm_monitor <executable>`` runs: ``get_package_prefix`` with the install's
    ``AMENT_PREFIX_PATH``, then ``lib/<package>/<executable>``; fails if it is no executable file."""
    from ament_index_python.packages import get_package_prefix

    saved = os.environ.get("AMENT_PREFIX_PATH")
    os.environ["AMENT_PREFIX_PATH"] = env["AMENT_PREFIX_PATH"]
    try:
        prefix = get_package_prefix(PACKAGE)
    finally:
        if saved is None:
            del os.environ["AMENT_PREFIX_PATH"]
        else:
            os.environ["AMENT_PREFIX_PATH"] = saved
    path = Path(prefix) / "lib" / PACKAGE / executable
    assert path.is_file() and os.access(path, os.X_OK), f"ros2 run would find no executable {path}"
    return path


class Workspace:
    """A colcon workspace ``<root>/src/mpm_monitor`` built into ``<root>/install``."""

    def __init__(self, root: Path):
        self.root = root
        self.src = root / "src" / PACKAGE
        self.install = root / "install"
        self.prefix = self.install / PACKAGE
        self.share = self.prefix / "share" / PACKAGE
        self.env = {}

    def build(self) -> None:
        clean_copy(self.src)
        cmd = [sys.executable, "-m", "colcon", "build", "--event-handlers", "console_direct-"]
        env = dict(os.environ, COLCON_HOME=str(self.root / "colcon_home"))  # no defaults.yaml of the user's
        env.pop("COLCON_DEFAULTS_FILE", None)
        res = subprocess.run(cmd, cwd=self.root, env=env, capture_output=True, text=True, timeout=240)
        if res.returncode != 0:
            pytest.fail(f"colcon build failed ({res.returncode}):\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}")
        self.env = sourced_env(self.install / "setup.bash")

    def run(self, args, timeout=60.0, **env) -> subprocess.CompletedProcess:
        """Run a command in the install's environment, from the workspace root (not the repository)."""
        return subprocess.run([str(a) for a in args], cwd=self.root, env=dict(self.env, **env),
                              capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    w = Workspace(tmp_path_factory.mktemp("colcon_ws"))
    w.build()
    return w


def test_the_copy_is_clean(ws):
    assert (ws.src / "package.xml").is_file() and (ws.src / "setup.cfg").is_file()
    assert not list(ws.src.rglob("*.egg-info")) and not (ws.src / ".venv").exists()


def test_every_executable_is_where_ros2_run_looks(ws):
    assert ws.env["AMENT_PREFIX_PATH"].split(os.pathsep)[0] == str(ws.prefix)
    for name in EXECUTABLES:
        assert ros2_run_path(ws.env, name) == ws.prefix / "lib" / PACKAGE / name
    assert sorted(p.name for p in (ws.prefix / "lib" / PACKAGE).iterdir()) == sorted(EXECUTABLES)
    assert not (ws.prefix / "bin").exists()  # where setuptools puts scripts without setup.cfg


def test_share_holds_package_xml_and_the_params_files(ws):
    assert (ws.share / "package.xml").read_bytes() == (ROOT / "package.xml").read_bytes()
    params = sorted(p.name for p in (ROOT / "config").glob("*.yaml"))
    assert params and sorted(p.name for p in (ws.share / "config").glob("*.yaml")) == params
    for name in params:
        assert (ws.share / "config" / name).read_bytes() == (ROOT / "config" / name).read_bytes()
    assert not (ws.share / "launch").exists()  # the launchers are no launch files
    assert (ws.install / PACKAGE / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file()


def test_the_install_environment_imports_the_installed_package(ws):
    res = ws.run([sys.executable, "-c", "import mpm_monitor.apps.launchers.common as c; "
                  "print(c.__file__); print(c.config_dir())"])
    assert res.returncode == 0, res.stderr
    module_file, config = res.stdout.split()
    assert Path(module_file).is_relative_to(ws.prefix / "lib")
    assert Path(config) == ws.share / "config"


def test_each_node_executable_starts_from_the_install(ws):
    """Each node answers bad parameters with its own one-line error and exit code 2: the script
    found its entry point in the install and got as far as the node's parameter check."""
    expected = {"plant_node": "give a model file (model_file) or a paper case",
                "mpc_node": "give a model file (model_file) or a paper case",
                "setpoint_node": "give a model file (model_file) or a paper case",
                "monitor_node": "give a model file (model_file) or a paper case",
                "recorder_node": "flush_period",
                "replay_node": "bag: expected a rosbag2 directory"}
    args = {"recorder_node": ["--ros-args", "-p", "flush_period:=1000.0"]}
    procs = {n: subprocess.Popen([str(ros2_run_path(ws.env, n))] + args.get(n, []), cwd=ws.root,
                                 env=dict(ws.env, ROS_AUTOMATIC_DISCOVERY_RANGE="OFF"),
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for n in NODES}
    for name, proc in procs.items():
        try:
            out, _ = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert proc.returncode == 2 and expected[name] in out, (name, proc.returncode, out[-2000:])
        assert "Traceback" not in out, (name, out[-2000:])


def test_launchers_and_the_cli_answer_help(ws):
    usages = [(n, f"usage: {n} ") for n in LAUNCHERS] + [("mpm_analyze", "usage: python -m mpm_monitor analyze")]
    for name, usage in usages:
        res = ws.run([ros2_run_path(ws.env, name), "--help"])
        assert res.returncode == 0 and res.stdout.startswith(usage), (name, res.stdout, res.stderr)


def test_a_launcher_from_the_install_runs_a_paper_case_with_its_installed_params(ws):
    """``ros2 run mpm_monitor suite_inprocess --case 3.2``: the four nodes of the install in one
    process, with the params file config/case_3_2.yaml from share/mpm_monitor (see the test above)."""
    res = ws.run([ros2_run_path(ws.env, "suite_inprocess"), "--case", "3.2", "--samples", "300", "--private",
                  "-p", "monitor.window_samples:=300", "-p", "monitor.min_samples:=200",
                  "-p", "monitor.analysis_period:=100"], timeout=120)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    assert "located rows: y1, y2; elements: (y1, u2), (y1, u3), (y2, u1)" in res.stdout


def test_the_monitor_from_the_install_answers_a_plain_publisher_with_diagnostics(ws, tmp_path):
    """``ros2 run mpm_monitor monitor_node --ros-args --params-file <share>/config/monitor.yaml -p
    model_file:=...`` on a domain of its own; this test publishes the three vector topics (no node of
    the package) and listens to the diagnostics."""
    import rclpy.node
    from sensor_msgs.msg import JointState

    ts = 0.005
    model = PlantModel(sample_time=ts, inputs=("u1", "u2"), outputs=("y1", "y2"), gain=[[1.0, 0.3], [0.2, 1.0]],
                       time_constant=[[0.05, 0.05], [0.05, 0.05]], delay=[[0.005, 0.0], [0.0, 0.005]])
    model_file = tmp_path / "unit_model.yaml"
    save_model(model, model_file)
    ns = f"/ws{os.getpid()}"
    cmd = [ros2_run_path(ws.env, "monitor_node"), "--ros-args", "-r", f"__ns:={ns}",
           "--params-file", ws.share / "config" / "monitor.yaml", "-p", f"model_file:={model_file}",
           "-p", "window_samples:=300", "-p", "min_samples:=200", "-p", "analysis_period:=100",
           "-p", "repair:=false", "-p", "republish_period:=0.2", "-p", "diagnostics_topic:=diagnostics"]
    with unique_domain(salt=11) as domain:
        ctx = domain_context(domain)
        node = rclpy.node.Node("plain_stack", context=ctx, namespace=ns)
        pubs = {c: node.create_publisher(JointState, c, vector_qos()) for c in ("setpoint", "input", "output")}
        summaries = []
        node.create_subscription(DiagnosticArray, "diagnostics",
                                 lambda m: summaries.extend(s for s in m.status if s.name == SUMMARY_NAME),
                                 diagnostics_qos())
        ex = make_executor(ctx, "single")
        ex.add_node(node)
        yc, uc = VectorCodec(model.outputs, "output"), VectorCodec(model.inputs, "input")
        rng = np.random.default_rng(5)
        running = threading.Event()
        running.set()

        def stack():
            t0 = time.monotonic()
            k = 0
            while running.is_set():
                time.sleep(max(0.0, t0 + k * ts - time.monotonic()))
                stamp = k * int(round(ts * 1e9))
                pubs["output"].publish(yc.encode(rng.normal(size=2), stamp))
                pubs["input"].publish(uc.encode(rng.normal(size=2), stamp))
                pubs["setpoint"].publish(yc.encode(np.sign(rng.normal(size=2)), stamp))
                k += 1

        def analysed():
            return any(s.level in (DiagnosticStatus.OK, DiagnosticStatus.WARN)
                       and int({kv.key: kv.value for kv in s.values}.get("analyses", "0")) >= 1 for s in summaries)

        log = tmp_path / "monitor.log"
        with open(log, "w") as fh:
            monitor = subprocess.Popen([str(a) for a in cmd], cwd=ws.root, stdout=fh, stderr=subprocess.STDOUT,
                                       env=dict(ws.env, ROS_DOMAIN_ID=str(domain),
                                                ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1"))
        thread = threading.Thread(target=stack, daemon=True)
        thread.start()
        try:
            ok = spin_until(ex, lambda: analysed() or monitor.poll() is not None, timeout=60.0)
            assert ok and analysed(), (f"no analysed diagnostics (monitor exit code {monitor.poll()}); last: "
                                       f"{[s.message for s in summaries[-3:]]}\n{log.read_text()[-3000:]}")
            assert all(s.hardware_id == f"{ns}/monitor" for s in summaries)
        finally:
            running.clear()
            thread.join(5)
            stop_process(monitor, 15.0)
            close_listener(ex, node, ctx)
