"""The README's worked examples are the tool's real output: each is run here and compared line by line.

The README says its examples are real runs; two of them had drifted from the tool (a block of the
report they lacked, a reworded header).  The printed lines are compared exactly (they round to a few
digits); the repaired model file's numbers to 1e-9 (their last digits follow the BLAS).
"""

import re
from pathlib import Path

import numpy as np
import yaml

from mpm_monitor.apps.cli import main

README = Path(__file__).resolve().parents[1] / "README.md"


def _block_after(marker: str) -> list:
    """The lines of the README's code block that holds ``marker``, from that line to the block's end."""
    lines = README.read_text().splitlines()
    at = next(k for k, line in enumerate(lines) if marker in line)
    end = next(k for k in range(at, len(lines)) if lines[k].startswith("```"))
    return lines[at:end]


def _outputs(block: list) -> list:
    """``[(command, [printed lines])]`` of a block whose commands start with ``$ `` (continuations end in ``\\``)."""
    out, k = [], 0
    while k < len(block):
        cmd = block[k][2:]
        while cmd.endswith("\\"):
            k += 1
            cmd = cmd[:-1] + block[k].strip()
        k += 1
        printed = []
        while k < len(block) and not block[k].startswith("$ "):
            printed.append(block[k])
            k += 1
        out.append((cmd, printed))
    return out


def _run(cmd: str, capsys) -> list:
    args = cmd.split()
    assert args[:3] == [".venv/bin/python", "-m", "mpm_monitor"], cmd
    capsys.readouterr()
    assert main(args[3:]) == 0
    return capsys.readouterr().out.splitlines()


def test_the_quick_analyze_example_is_the_tools_output(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    steps = _outputs(_block_after("$ .venv/bin/python -m mpm_monitor simulate --case 3.2 --samples 3000 --seed 7"))
    assert [c.split()[3] for c, _ in steps[:2]] == ["simulate", "analyze"] and steps[2][0] == "cat repaired.yaml"
    for cmd, printed in steps[:2]:
        assert _run(cmd, capsys) == printed, cmd
    shown = yaml.safe_load("\n".join(steps[2][1]))
    written = yaml.safe_load((tmp_path / "repaired.yaml").read_text())
    assert shown.keys() == written.keys()
    for key, value in shown.items():
        if isinstance(value, list) and key not in ("inputs", "outputs"):
            np.testing.assert_allclose(np.array(written[key], float), np.array(value, float), rtol=1e-9)
        else:
            assert written[key] == value, key
    assert (tmp_path / "report.json").is_file() and (tmp_path / "report_dir").is_dir()


def test_the_gaps_example_is_the_tools_output(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    block = _block_after(".venv/bin/python -m mpm_monitor simulate --case 3.2 --csv log.csv")
    simulate, wrote, sed, analyze = block[:4]
    assert _run(simulate, capsys) == [wrote]
    dropped = [int(t) for t in re.findall(r"/\^(\d+),/d", sed)]
    assert dropped == [1200, 1201, 1202, 2500]
    lines = (tmp_path / "log.csv").read_text().splitlines(keepends=True)
    (tmp_path / "gappy.csv").write_text("".join(line for line in lines if line.split(",")[0] not in
                                                {str(t) for t in dropped}))
    assert _run(analyze, capsys) == block[4:]
