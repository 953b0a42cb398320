"""A ``--params-file`` that rcl cannot read is said in one line of ours, and rcl prints nothing.

rcl parses the ``--params-file`` arguments in ``rclpy.init``; a bad one made it print its own ``[ERROR] [...]
[rcl]: Failed to parse global arguments`` line before the node's ``error: ...`` line (a file of
``name: value`` lines, a node without ``ros__parameters``, a list ``[0, 0.5]`` of an integer and a double),
and a date that is not one (``2001-13-45``) ended the check itself in a traceback.  The check of
:mod:`mpm_monitor.nodes.params_file_check` reads them first, by the ``--ros-args`` grammar; a node process
ends with exit code 2 and one line; a good file is read by rcl as before.
"""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from ros_domains import unique_domain

from bench.ros_domain import domain_env
from mpm_monitor.nodes.params_file_check import PARAMS_FILE_FORM, params_file_problem, ros_params_files

pytestmark = pytest.mark.timeout(180)

ROOT = Path(__file__).resolve().parent.parent
#: The exit code of a node that refuses its parameters (run_node).
BAD_PARAMETER = 2

#: Files rcl refuses, and the start of what the check says after ``--params-file PATH: ``.
BAD = {
    "flat": ("case: '3.2'\nmode: step\n", "line 1: key 'case' holds '3.2' outside any node's ros__parameters"),
    "no_ros_parameters": ("/**/setpoint:\n  case: '3.2'\n",
                          "line 2: key 'case' holds '3.2' outside any node's ros__parameters"),
    "top_list": ("- case: '3.2'\n", "line 1: a list at the top level"),
    "parameters_nothing": ("/**/setpoint:\n  ros__parameters:\n",
                           "line 2: ros__parameters of /**/setpoint holds nothing, not a mapping"),
    "parameters_top": ("ros__parameters:\n  case: '3.2'\n", "line 1: ros__parameters with no node name above it"),
    "node_list": ("setpoint: []\n", "line 1: key 'setpoint' holds a list outside any node's ros__parameters"),
    "beside_parameters": ("setpoint:\n  ros__parameters:\n    case: '3.2'\n  mode: step\n",
                          "line 4: key 'mode' holds 'step' outside any node's ros__parameters"),
    "bad_node_name": ("set-point:\n  ros__parameters:\n    case: '3.2'\n", "line 1: node name 'set-point' of"),
    "bad_namespace": ("/1ns/setpoint:\n  ros__parameters:\n    case: '3.2'\n",
                      "line 1: namespace part '1ns' of '/1ns/setpoint'"),
    "repeated_slash": ("//setpoint:\n  ros__parameters:\n    case: '3.2'\n", "line 1: node name '//setpoint'"),
    "empty_key": ("'':\n  ros__parameters:\n    case: '3.2'\n", "line 1: an empty key"),
    "alias": ("a:\n  ros__parameters: &p\n    case: '3.2'\nb:\n  ros__parameters: *p\n", "line 5: an alias (*p)"),
    "mixed_list": ("/**/setpoint:\n  ros__parameters:\n    levels: [0, 0.5]\n",
                   "line 3: the list of parameter levels mixes integer '0' and double '0.5'"),
    "no_value": ("/**/setpoint:\n  ros__parameters:\n    case:\n    mode: step\n",
                 "line 3: parameter case has no value"),
    "unclosed": ("/**/setpoint:\n  ros__parameters: [unclosed\n",
                 "not valid YAML at line 3, column 1: expected ',' or ']', but got '<stream end>'; expected a ROS"),
    "tab": ("/**/setpoint:\n\tros__parameters: {}\n",
            "not valid YAML at line 2, column 1: found character '\\t' that cannot start any token; expected"),
    "control_character": ("/**/setpoint:\n  ros__parameters:\n    case: \x01\n",
                          "not valid YAML at character 44: special characters are not allowed; expected"),
}

#: Files rcl reads (the wildcard and namespace forms, lists of one type, values PyYAML would make dates of).
GOOD = {
    "wildcard": "/**:\n  ros__parameters:\n    case: '3.2'\n",
    "wildcard_node": "/**/setpoint:\n  ros__parameters:\n    case: '3.2'\n    mode: step\n",
    "nested": "ns:\n  sub:\n    setpoint:\n      ros__parameters:\n        case: '3.2'\n",
    "star": "/*/setpoint:\n  ros__parameters:\n    case: '3.2'\n",
    "two_nodes": "setpoint:\n  ros__parameters:\n    seed: 3\nplant:\n  ros__parameters: {}\n",
    "lists": ("/**:\n  ros__parameters:\n    a: [0.0, 0.5, 1e3, .inf]\n    b: [1, 0x1F, 017]\n"
              "    c: [a, 'b', \"1\"]\n    d: [true, no, On]\n    e: []\n    f: [inf, 1.5]\n"),
    "not_a_date": "/**:\n  ros__parameters:\n    when: 2001-13-45\n    tag: !!binary aGVsbG8=\n",
    "param_namespaces": "/**:\n  ros__parameters:\n    g:\n      a: 1\n      h: {b: [1, 2]}\n",
    "anchor_only": "/**:\n  ros__parameters:\n    a: &x 1\n",
}


def _write(tmp_path, name: str, text: str) -> str:
    path = tmp_path / f"{name}.yaml"
    path.write_text(text, encoding="utf-8")
    return str(path)


# ------------------------------------------------------------------------------ the command line
@pytest.mark.parametrize("args, files", [
    (["node", "--ros-args", "--params-file", "a.yaml"], ["a.yaml"]),
    (["node", "--params-file", "a.yaml"], []),                                        # not a ROS argument
    (["node", "--ros-args", "-p", "x:=1", "--", "--params-file", "a.yaml"], []),      # after the section's end
    (["node", "--ros-args", "--", "--ros-args", "--params-file", "b.yaml"], ["b.yaml"]),
    (["node", "--ros-args", "-p", "--params-file", "a.yaml"], []),                    # -p's rule, then a stray arg
    (["node", "--ros-args", "-r", "__node:=x", "--params-file", "a.yaml", "--log-level", "debug",
      "--enable-rosout-logs", "--params-file", "b.yaml"], ["a.yaml", "b.yaml"]),
    (["node", "--ros-args", "--params-file"], [None]),
    (None, []),
])
def test_the_params_files_are_those_of_the_ros_args_sections(args, files):
    assert ros_params_files(args) == files


def test_a_params_file_flag_without_a_path_is_one_line():
    assert params_file_problem(["node", "--ros-args", "--params-file"]) == \
        "--params-file: expected the path of a params file after it (it ends the command line)"


def test_a_bad_file_outside_the_ros_args_is_not_checked(tmp_path):
    bad = _write(tmp_path, "flat", BAD["flat"][0])
    assert params_file_problem(["node", "--params-file", bad, "--ros-args", "-p", "case:=3.2"]) == ""
    assert params_file_problem(["node", "--ros-args", "--params-file", bad]) != ""


# ---------------------------------------------------------------------------------- the files
@pytest.mark.parametrize("name", sorted(BAD))
def test_a_bad_params_file_is_one_line_naming_the_file_and_what_was_expected(tmp_path, name):
    text, said = BAD[name]
    path = _write(tmp_path, name, text)
    problem = params_file_problem(["node", "--ros-args", "--params-file", path])
    assert problem.startswith(f"--params-file {path}: {said}"), problem
    assert "expected " in problem and "\n" not in problem and len(problem) < 400


def test_the_structure_messages_say_the_form_of_a_params_file(tmp_path):
    path = _write(tmp_path, "flat", BAD["flat"][0])
    assert params_file_problem(["--ros-args", "--params-file", path]) == (
        f"--params-file {path}: line 1: key 'case' holds '3.2' outside any node's ros__parameters: expected "
        f"{PARAMS_FILE_FORM}")
    assert PARAMS_FILE_FORM == ("a ROS params file, node_name: {ros__parameters: {name: value, ...}} per node "
                                "(node_name may be /**/name or /**)")


def test_unreadable_empty_endless_deep_and_not_utf8_files_are_one_line(tmp_path):
    missing = str(tmp_path / "none.yaml")
    assert params_file_problem(["--ros-args", "--params-file", missing]) == \
        f"--params-file {missing}: cannot read it: No such file or directory"
    assert params_file_problem(["--ros-args", "--params-file", str(tmp_path)]) == \
        f"--params-file {tmp_path}: cannot read it: Is a directory"
    empty = _write(tmp_path, "empty", "# nothing\n")
    assert params_file_problem(["--ros-args", "--params-file", empty]) == \
        f"--params-file {empty}: empty (no YAML document): expected {PARAMS_FILE_FORM}"
    latin = tmp_path / "latin.yaml"
    latin.write_bytes("/**:\n  ros__parameters:\n    unit: '°C'\n".encode("latin-1"))
    assert params_file_problem(["--ros-args", "--params-file", str(latin)]) == (
        f"--params-file {latin}: not UTF-8 text (byte 0xb0 at offset 35): expected {PARAMS_FILE_FORM}")
    assert params_file_problem(["--ros-args", "--params-file", "/dev/zero"]) == \
        f"--params-file /dev/zero: longer than 16,777,216 bytes: expected {PARAMS_FILE_FORM}"
    deep = _write(tmp_path, "deep", "/**:\n  ros__parameters:\n    a: " + "[" * 3000 + "]" * 3000 + "\n")
    assert params_file_problem(["--ros-args", "--params-file", deep]) == \
        f"--params-file {deep}: lists or mappings nested too deeply: expected {PARAMS_FILE_FORM}"


@pytest.mark.parametrize("name", sorted(GOOD))
def test_a_good_params_file_passes(tmp_path, name):
    assert params_file_problem(["--ros-args", "--params-file", _write(tmp_path, name, GOOD[name])]) == ""


def test_the_shipped_params_files_pass():
    files = sorted((ROOT / "config").glob("*.yaml"))
    assert len(files) >= 6
    args = ["node", "--ros-args"] + [a for f in files for a in ("--params-file", str(f))]
    assert params_file_problem(args) == ""


def test_rcl_refuses_the_bad_files_and_reads_the_good_ones(tmp_path, monkeypatch, capfd):
    """The check refuses no file rcl reads: each bad file is refused by ``rclpy.init`` too, each good one read."""
    pytest.importorskip("rclpy")
    import rclpy
    from rclpy.context import Context

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")

    def rcl_reads(path: str) -> bool:
        context = Context()
        try:
            rclpy.init(args=["node", "--ros-args", "--params-file", path], context=context)
        except Exception:            # noqa: BLE001 - rcl's RCLError
            return False
        context.try_shutdown()
        return True

    for name, (text, _) in BAD.items():
        assert not rcl_reads(_write(tmp_path, name, text)), name
    for name, text in GOOD.items():
        assert rcl_reads(_write(tmp_path, name, text)), name
    assert "[rcl]" in capfd.readouterr().err          # rcl's own line, which the nodes now never reach


# ----------------------------------------------------------------------------- node processes
def _node_env(domain: int) -> dict:
    return dict(os.environ, **domain_env(domain), RCUTILS_LOGGING_BUFFERED_STREAM="0", PYTHONUNBUFFERED="1")


@pytest.mark.parametrize("name", ["flat", "no_ros_parameters", "mixed_list", "unclosed"])
def test_a_node_started_with_a_bad_params_file_says_one_line_and_exits_2(tmp_path, name):
    path = _write(tmp_path, name, BAD[name][0])
    with unique_domain(salt=len(name)) as domain:
        done = subprocess.run([sys.executable, "-m", "mpm_monitor.nodes.entry", "setpoint_node", "--ros-args",
                               "--params-file", path], cwd=ROOT, env=_node_env(domain), capture_output=True,
                              text=True, timeout=120)
    assert done.returncode == BAD_PARAMETER, done.stderr
    assert "[rcl]" not in done.stderr and "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"error: --params-file {path}: {BAD[name][1]}"), lines[0]


def test_a_node_started_with_a_good_params_file_runs_with_its_values(tmp_path):
    """rcl still reads a good file: the setpoint node starts with the file's ``mode: step`` (its log line says
    so) and stops on SIGINT with exit code 0."""
    path = _write(tmp_path, "good", "/**/setpoint:\n  ros__parameters:\n    case: '3.2'\n    mode: step\n")
    with unique_domain(salt=7) as domain:
        proc = subprocess.Popen([sys.executable, "-m", "mpm_monitor.nodes.entry", "setpoint_node", "--ros-args",
                                 "--params-file", path], cwd=ROOT, env=_node_env(domain), stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        lines: list = []
        reader = threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")), daemon=True)
        reader.start()
        try:
            deadline = time.monotonic() + 60
            while not any("step setpoints on" in line for line in lines):
                assert proc.poll() is None and time.monotonic() < deadline, "".join(lines)
                time.sleep(0.05)
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=30) == 0, "".join(lines)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            reader.join(timeout=5)
    text = "".join(lines)
    assert "error" not in text.lower() and "[rcl]" not in text, text
