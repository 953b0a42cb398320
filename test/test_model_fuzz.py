"""Model files found by a fuzz campaign of ``analyze`` / ``simulate`` (mutated valid models of every structure):
each gave a crash, a traceback or an unclear message, and is now one line naming the file and the key, exit 2.
"""

import subprocess
import sys

import pytest

#: A valid model with lists of numbers (read by the one-pass number-list parser).
NUMBERS_HEAD = "sample_time: 1\ninputs: [u1]\noutputs: [y1]\ngain: [[1.5]]\ntime_constant: [[2]]\ndelay: [[0]]\n"

_LOAD = ("import sys\nfrom mpm_monitor.io.model_file import load_model\nfrom mpm_monitor.core.errors import "
         "ModelFileError\ntry:\n    load_model(sys.argv[1])\nexcept ModelFileError as exc:\n    print(exc)\n")


@pytest.mark.parametrize("deep", [
    "name: " + "[" * 100000 + "]" * 100000 + "\n",              # flow sequences
    "name: " + "{a: " * 30000 + "}" * 30000 + "\n",             # flow mappings
    "name:\n" + "- " * 30000 + "x\n",                          # block sequences, compact on one line
])
def test_deep_nesting_beside_lists_of_numbers_is_refused_in_one_line(tmp_path, deep):
    """A model whose lists of numbers the one-pass parser replaces (any real model) handed the rest of the text to
    libyaml without the nesting check: 30,000 levels crashed the process (segmentation fault, exit -11/139, no
    message).  In a child process, so that a crash is a failure of this test, not of the run."""
    path = tmp_path / "deep.yaml"
    path.write_text(NUMBERS_HEAD + deep, encoding="utf-8")
    out = subprocess.run([sys.executable, "-c", _LOAD, str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, (out.returncode, out.stderr[-500:])
    assert out.stdout.strip() == f"{path}: not a model file: lists or mappings nested too deeply"


SIMULATED = "sample_time: 1\ninputs: [u1, u2]\noutputs: [y1, y2]\ngain: [[1, 0.5], [0.3, 2]]\n" \
            "time_constant: [[5, 4], [3, 6]]\n"


@pytest.mark.parametrize("delay, was", [(100000, "out of memory, exit 1"), (2 ** 31 - 1, "a traceback of numpy's")])
@pytest.mark.parametrize("flag", ["--plant", "--model"])
def test_simulate_refuses_a_dead_time_its_state_space_cannot_hold(tmp_path, capsys, delay, was, flag):
    """The simulation's state space is dense: a dead time of 100,000 samples asked numpy for 75 GiB (``out of memory``,
    blamed on a long log, exit 1), one of 2^31 - 1 samples gave a traceback, and 30,000 ran with 14 GB.  The line
    names the flag and file of the model that has it."""
    from mpm_monitor.apps.cli import main

    path, fine = tmp_path / "long.yaml", tmp_path / "fine.yaml"
    path.write_text(SIMULATED + f"delay: [[1, 2], [{delay}, 1]]\n", encoding="utf-8")
    fine.write_text(SIMULATED + "delay: [[1, 2], [3, 1]]\n", encoding="utf-8")
    plant, model = (path, fine) if flag == "--plant" else (fine, path)
    code = main(["simulate", "--plant", str(plant), "--model", str(model), "--samples", "50",
                 "--csv", str(tmp_path / "log.csv")])
    err = capsys.readouterr().err
    assert code == 2, (was, code, err)
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err.startswith(f"error: {flag} {path}: key 'delay': row 2 (y2), column 1 (u1): a dead time of {delay:,} "
                          f"samples (the model's longest) makes its state space"), err
    assert "a simulation holds at most 16,384" in err
    assert not (tmp_path / "log.csv").exists()


def test_state_space_itself_refuses_what_a_simulation_cannot_hold(tmp_path):
    """The core's own refusal, for callers other than the command line (its message says ``simulation``)."""
    from mpm_monitor.core.discretize import check_state_count, state_space
    from mpm_monitor.core.errors import ModelFileError
    from mpm_monitor.io.model_file import load_model

    def parse_model_text(text):
        (tmp_path / "m.yaml").write_text(text, encoding="utf-8")
        return load_model(tmp_path / "m.yaml")

    model = parse_model_text(SIMULATED + "delay: [[1, 2], [20000, 1]]\n")
    for f in (check_state_count, state_space):
        with pytest.raises(ModelFileError, match=r"^simulation: key 'delay': row 2 \(y2\), column 1 \(u1\): a dead "
                                                 r"time of 20,000 samples"):
            f(model)
    check_state_count(parse_model_text(SIMULATED + "delay: [[1, 2], [2000, 1]]\n"))


def test_simulate_refuses_a_step_response_its_state_space_cannot_hold(tmp_path, capsys):
    from mpm_monitor.apps.cli import main

    n = 20000
    coefficients = ", ".join(str(k / n) for k in range(n))      # a response that moves at every sample
    path = tmp_path / "plant.yaml"
    path.write_text(f"sample_time: 1\ninputs: [u1]\noutputs: [y1]\nstep_response:\n  length: {n}\n  coefficients:\n"
                    f"  - [[{coefficients}]]\n", encoding="utf-8")
    code = main(["simulate", "--plant", str(path), "--model", str(path), "--samples", "50",
                 "--csv", str(tmp_path / "log.csv")])
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.splitlines()) == 1
    assert err.startswith(f"error: --plant {path}: key 'step_response': row 1 (y1), column 1 (u1): a response of 20,000 "
                          "coefficients (the model's longest)"), err


def test_simulate_keeps_a_dead_time_that_fits(tmp_path, capsys):
    """Control: 2,000 samples of dead time still simulate."""
    from mpm_monitor.apps.cli import main

    path = tmp_path / "plant.yaml"
    path.write_text(SIMULATED + "delay: [[1, 2], [2000, 1]]\n", encoding="utf-8")
    code = main(["simulate", "--plant", str(path), "--model", str(path), "--samples", "50",
                 "--csv", str(tmp_path / "log.csv")])
    assert code == 0, capsys.readouterr().err


def test_a_null_key_is_named_as_null(tmp_path):
    """``~: 2`` was said to be the unknown key 'None', a name the file does not hold."""
    from mpm_monitor.core.errors import ModelFileError
    from mpm_monitor.io.model_file import load_model

    path = tmp_path / "null.yaml"
    path.write_text(SIMULATED + "delay: [[0, 0], [0, 0]]\n~: 2\n", encoding="utf-8")
    with pytest.raises(ModelFileError, match=r"null\.yaml: a key that is null \(~ or null\): a model file holds only "
                                             r"the keys sample_time, inputs"):
        load_model(path)
