"""bench.stages: the stages of one analyze timed in a fresh interpreter (a small case, one repeat)."""

import pytest

from bench import stages


def test_the_stages_of_a_small_analysis_are_timed_and_nest():
    out = stages.run([(3, 3)], repeats=1, log=lambda *_: None)
    s = out["sizes"]["3x3"]["summary"]
    st = s["stages"]
    assert s["located"]                                          # the case has one element off
    assert st["detection"]["calls"] == 2 and st["repair"]["calls"] == 1   # before and after the repair
    for label in ("model run", "regressions", "row test", "element test", "  moments of the responses",
                  "detectability", "experiment"):
        assert st[label]["calls"] >= 1 and st[label]["total_s"] > 0, label
    first = st["detection"]["each_s"][0]
    inside = sum(st[k]["each_s"][0] for k in stages.INSIDE_DETECTION)
    assert 0 < inside <= first and s["rest_of_first_detection_s"] == pytest.approx(first - inside)
    assert st["  moments of the responses"]["total_s"] <= st["element test"]["total_s"]
    assert s["analyze_s"] >= first + st["repair"]["total_s"]
    assert "3x3: analyze" in stages.format_size("3x3", s)


def test_with_two_processes_the_parent_waits_for_the_detectability_it_left_to_the_child():
    out = stages.run([(3, 3)], repeats=1, log=lambda *_: None, jobs=2)
    st = out["sizes"]["3x3"]["summary"]["stages"]
    assert out["jobs"] == 2 and st["repair"]["calls"] == 1
    assert st["detectability"]["calls"] == 0                    # computed in the child, beside the repair
    assert st["waiting for the child"]["calls"] >= 1


def test_bad_sizes_are_refused():
    with pytest.raises(SystemExit):
        stages.main(["--sizes", "20by20"])
    with pytest.raises(SystemExit):
        stages.main(["--repeats", "0"])
    with pytest.raises(SystemExit):
        stages.main(["--jobs", "0"])
