"""bench.paired: runs in turn, compiled copies of the code, the ratio pair by pair (no timing target)."""

import subprocess

import pytest

from bench import paired
from bench.perf import stale_bytecode


def test_runs_alternate_after_one_warm_up_each_and_the_ratio_is_taken_pair_by_pair():
    calls = []
    a_walls, b_walls = iter([9.0, 1.0, 2.0, 3.0]), iter([9.0, 2.0, 2.0, 2.0])

    def run_a():
        calls.append("a")
        return next(a_walls), 100.0, 0

    def run_b():
        calls.append("b")
        return next(b_walls), 120.0, 1

    got = paired.pair_runs(run_a, run_b, 3)
    assert calls == ["a", "b"] * 4
    assert got["a_walls"] == [1.0, 2.0, 3.0] and got["b_walls"] == [2.0, 2.0, 2.0]    # the warm-ups left out
    assert got["a_wall_s"] == 2.0 and got["b_wall_s"] == 2.0
    assert (got["ratio_median"], got["ratio_min"], got["ratio_max"]) == (1.0, 0.5, 1.5)
    assert got["a_max_rss_mib"] == 100.0 and got["b_max_rss_mib"] == 120.0
    assert got["a_exit"] == [0] and got["b_exit"] == [1]
    assert "x1.000" in paired.format_size("3x3", dict(got, reports_identical=True))


def test_a_revision_is_checked_out_compiled_and_imported_then_removed(tmp_path):
    folder = tmp_path / "head"
    tree = paired.compiled_tree("HEAD", folder)
    try:
        assert tree == folder
        assert stale_bytecode(tree / "mpm_monitor") == 0      # every module has its bytecode
        assert paired.imported_from(tree) == (tree / "mpm_monitor").resolve()
    finally:
        paired.remove_tree(tree)
    assert not folder.exists()
    listed = subprocess.run(["git", "-C", str(paired.REPO), "worktree", "list"], capture_output=True, text=True).stdout
    assert str(folder) not in listed


def test_an_unknown_revision_is_refused_on_one_line(tmp_path):
    with pytest.raises(RuntimeError, match="git worktree add no-such-revision-x") as got:
        paired.compiled_tree("no-such-revision-x", tmp_path / "x")
    assert "\n" not in str(got.value)


@pytest.mark.parametrize("argv", [["HEAD", "--sizes", "20by20"], ["HEAD", "--pairs", "0"], ["HEAD", "--jobs", "0"], []])
def test_bad_arguments_are_refused(argv):
    with pytest.raises(SystemExit):
        paired.main(argv)
