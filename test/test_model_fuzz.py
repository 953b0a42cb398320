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
