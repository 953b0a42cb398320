"""Bag inputs of the command line fuzzed from outside (``analyze --bag``, ``export``, ``recover``): what got through.

Every bad bag is one line ``error: ...`` on stderr naming the bag (and the key, topic or message), exit code 2,
never a traceback, a hang or a line of hundreds of kilobytes.

- A ``metadata.yaml`` whose topic entry counts ``message_count: x`` or names a topic by a number: a ``TypeError``
  traceback (exit 1) from the topic lookup; a ``relative_file_paths`` that is a string, not a list: rosbags
  listed each of its letters as a missing file.
- A storage file that is a named pipe: the reader waited on it for ever (a directory or a device was said with
  the hint of a truncated recording).
- A ``metadata.yaml`` that is not UTF-8, or that nests 100,000 deep, got the hint of a truncated storage file
  (``recover``), the second after seconds of parsing; a version or storage plugin rosbags does not read was
  worded "please report issue" with the same hint; a missing key as ``KeyError('version')``.
- A schema record encoded other than ros2msg or ros2idl, or naming a type nothing defines: rosbags' bare
  ``KeyError`` text (``'jsonschema'``) with the hint of a truncated storage file.
- ``--bag`` a symbolic link to itself: a ``RuntimeError`` traceback from resolving it.
- A channel name holding a line break split the message over two lines (a terminal escape in one went to the
  terminal); a message of 20,000 names was named in one line of 200 kB, after 10 s of matching names.
"""

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import StoragePlugin, Writer

from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.io import bags as bag_io

REPO = Path(__file__).resolve().parents[1]
TS = bag_io.default_typestore()
JS = TS.types["sensor_msgs/msg/JointState"]
HEADER = TS.types["std_msgs/msg/Header"]
TIME = TS.types["builtin_interfaces/msg/Time"]
NAMES = {"setpoint": ("y1",), "input": ("u1",), "output": ("y1",)}


def _bag(path, n=20, names=None):
    """A bag of /setpoint, /input and /output, one JointState each per sample (0.5 s apart); ``names(role, k)``
    gives a message's channel names (default :data:`NAMES`)."""
    rng = np.random.default_rng(1)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {role: w.add_connection(f"/{role}", JS.__msgtype__, typestore=TS) for role in NAMES}
        for k in range(n):
            stamp = 100 * 10**9 + k * 500_000_000
            for role, conn in conns.items():
                chans = list(names(role, k) if names else NAMES[role])
                msg = JS(header=HEADER(stamp=TIME(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=""),
                         name=chans, position=rng.normal(size=len(chans)), velocity=np.zeros(0), effort=np.zeros(0))
                w.write(conn, stamp, TS.serialize_cdr(msg, JS.__msgtype__))
    return path


def _model(tmp_path) -> Path:
    """A model file of the channels of :data:`NAMES` (sample time 0.5 s)."""
    from mpm_monitor.core.model import PlantModel
    from mpm_monitor.io.model_file import save_model

    save_model(PlantModel(sample_time=0.5, inputs=("u1",), outputs=("y1",), gain=[[1.0]], time_constant=[[2.0]],
                          delay=[[0.0]]), tmp_path / "model.yaml")
    return tmp_path / "model.yaml"


def _export(capsys, bag, tmp_path, *extra):
    code = cli_main(["export", "--bag", str(bag), "--csv", str(tmp_path / "out.csv"), *extra])
    err = capsys.readouterr().err
    return code, err


def _one_line(code, err, bag, *words):
    assert code == 2, err
    assert len(err.splitlines()) == 1 and err.startswith(f"error: {bag}"), err
    assert "Traceback" not in err and len(err) < 1000, err
    for w in words:
        assert w in err, err


def _edit_metadata(bag, edit):
    meta = bag / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    edit(doc["rosbag2_bagfile_information"])
    meta.write_text(yaml.safe_dump(doc))


@pytest.mark.parametrize("edit, words", [
    (lambda i: i["topics_with_message_count"][1].update(message_count="x"),
     "metadata.yaml: key 'topics_with_message_count[1].message_count': expected a whole number >= 0, got 'x'"),
    (lambda i: i["topics_with_message_count"][1]["topic_metadata"].update(name=5),
     "metadata.yaml: key 'topics_with_message_count[1].topic_metadata.name': expected a string, got 5"),
    (lambda i: i.update(relative_file_paths=i["relative_file_paths"][0]),
     "metadata.yaml: key 'relative_file_paths': expected a list of file names, got 'bag.mcap'"),
], ids=["count not a number", "topic name a number", "file list a string"])
def test_metadata_entries_of_the_wrong_kind_are_named_by_their_key(tmp_path, capsys, edit, words):
    bag = _bag(tmp_path / "bag")
    _edit_metadata(bag, edit)
    for extra in ((), ("--topics", "setpoint", "input", "output")):
        _one_line(*_export(capsys, bag, tmp_path, *extra), bag, words)


@pytest.mark.parametrize("kind, make", [
    ("a named pipe", os.mkfifo),
    ("a directory", os.mkdir),
    ("a device", lambda p: os.symlink("/dev/zero", p)),
], ids=["fifo", "directory", "device"])
def test_a_storage_file_that_is_not_a_file_is_refused_without_waiting_on_it(tmp_path, kind, make):
    bag = _bag(tmp_path / "bag")
    (bag / "bag.mcap").unlink()
    make(bag / "bag.mcap")
    started = time.monotonic()
    try:
        run = subprocess.run([sys.executable, "-m", "mpm_monitor", "export", "--bag", str(bag), "--csv",
                              str(tmp_path / "out.csv")], capture_output=True, text=True, timeout=60, cwd=REPO)
    except subprocess.TimeoutExpired:
        pytest.fail(f"export of a bag whose storage file is {kind} still ran after 60 s")
    assert time.monotonic() - started < 60
    _one_line(run.returncode, run.stderr, bag,
              f"storage file 'bag.mcap' is {kind}, not a file: expected the storage file metadata.yaml names")
    assert "truncated" not in run.stderr


@pytest.mark.parametrize("damage, words", [
    (lambda meta: meta.write_bytes(meta.read_text().encode("utf-16")),
     ("cannot read bag: metadata.yaml is not UTF-8 text (byte 0) (expected metadata.yaml as rosbag2 writes it)",)),
    (lambda meta: meta.write_text(meta.read_text() + "x: " + "[" * 100000 + "]" * 100000 + "\n"),
     ("cannot read bag: metadata.yaml nests lists or mappings more than 100 deep (expected metadata.yaml as "
      "rosbag2 writes it)",)),
    (lambda meta: meta.write_text(meta.read_text().replace("version: 9", "version: 99")),
     ("cannot read bag: Rosbag2 version 99 not supported. (expected metadata.yaml of a bag this reader reads: "
      "metadata version 9 or lower",)),
    (lambda meta: meta.write_text(meta.read_text().replace("storage_identifier: mcap", "storage_identifier: hdf5")),
     ("cannot read bag: Storage plugin 'hdf5' not supported. (expected metadata.yaml of a bag this reader reads: ",
      "MCAP or SQLite 3 storage")),
    (lambda meta: meta.write_text(meta.read_text().replace("version: 9", "versio: 9")),
     ("cannot read bag: metadata.yaml lacks the key 'version' (expected metadata.yaml as rosbag2 writes it)",)),
], ids=["utf-16", "nested 100,000 deep", "version 99", "storage plugin", "key missing"])
def test_a_metadata_fault_is_said_as_one_without_the_truncation_hint(tmp_path, capsys, damage, words):
    bag = _bag(tmp_path / "bag")
    damage(bag / "metadata.yaml")
    started = time.monotonic()
    code, err = _export(capsys, bag, tmp_path)
    _one_line(code, err, bag, *words)
    assert "truncated" not in err and "please report" not in err and "KeyError" not in err
    assert time.monotonic() - started < 5        # the nesting: 15 s of two parsers reaching their recursion limit


@pytest.mark.parametrize("argv", [
    ["export", "--bag", "{loop}", "--csv", "{tmp}/out.csv"],
    ["analyze", "--model", "{tmp}/model.yaml", "--bag", "{loop}", "--json", "{tmp}/r.json"],
], ids=["export", "analyze"])
def test_a_bag_path_that_links_to_itself_is_one_line(tmp_path, capsys, argv):
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    _model(tmp_path)
    code = cli_main([a.format(loop=loop, tmp=tmp_path) for a in argv])
    err = capsys.readouterr().err
    _one_line(code, err, loop)


@pytest.mark.parametrize("name, shown", [
    ("u1\nfoo", r"'u1\nfoo'"),
    ("\x1b[31mu1", r"'\x1b[31mu1'"),
], ids=["line break", "terminal escape"])
def test_a_channel_name_with_a_control_character_is_shown_escaped_on_one_line(tmp_path, capsys, name, shown):
    bag = _bag(tmp_path / "bag", names=lambda role, k: (name,) if role == "input" else NAMES[role])
    code, err = _export(capsys, bag, tmp_path, "--model", str(_model(tmp_path)))
    _one_line(code, err, bag, f"topic '/input': message 1 (stamp 100 s) has channel names [{shown}], expected "
                              f"the inputs [u1]")
    assert "\x1b" not in err


def test_a_message_of_thousands_of_names_is_named_in_a_short_line_and_soon(tmp_path, capsys):
    many = ("u1",) + tuple(f"c{i}" for i in range(20000))
    bag = _bag(tmp_path / "bag", names=lambda role, k: many if role == "input" and k == 0 else NAMES[role])
    started = time.monotonic()
    code, err = _export(capsys, bag, tmp_path)
    _one_line(code, err, bag, "topic '/input': message 2 (stamp 100.5 s) has channel names [u1], expected the "
                              "inputs [u1, c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, ... (20001 in all)]")
    assert time.monotonic() - started < 5


@pytest.mark.parametrize("old, new, words", [
    (b"ros2msg", b"jsonsch", "cannot read bag: the storage file's schema records name 'jsonsch', a schema encoding "
                             "or message type this reader does not know (expected message definitions as rosbag2 "
                             "writes them: encoded ros2msg or ros2idl)"),
    (b"string[] name", b"strung[] name", "cannot read bag: the storage file's schema records name "
                                         "'sensor_msgs/msg/strung', a schema encoding or message type"),
], ids=["encoding", "type"])
def test_a_schema_this_reader_does_not_know_is_named_as_such(tmp_path, capsys, old, new, words):
    from mpm_monitor.io.bags import read_raw_messages
    from mpm_monitor.io.bags.write import BagWriter

    raw = read_raw_messages(_bag(tmp_path / "src"), list(NAMES))
    w = BagWriter(tmp_path / "bag", fsync=False)         # stores the message definitions (rosbags' writer too)
    for m in raw:
        if not w.has_topic(m.topic):
            w.add_topic(m.topic, m.msgtype)
        w.write(m.topic, m.log_time, m.data)
    w.close()
    mcap = tmp_path / "bag" / "bag.mcap"
    data = mcap.read_bytes()
    assert old in data
    mcap.write_bytes(data.replace(old, new))
    code, err = _export(capsys, tmp_path / "bag", tmp_path)
    _one_line(code, err, tmp_path / "bag", words)
    assert "truncated" not in err


def test_a_storage_file_of_its_magic_bytes_alone_is_said_to_end_before_any_record(tmp_path, capsys):
    """An .mcap holding only the 8 magic bytes (a recorder killed at once): rosbags' words were Python's
    ``ord() expected a character, but string of length 0 found``."""
    bag = _bag(tmp_path / "bag")
    next(bag.glob("*.mcap")).write_bytes(b"\x89MCAP0\r\n")
    code, err = _export(capsys, bag, tmp_path)
    _one_line(code, err, bag, "the storage file ends after its first bytes, before any record", "recover")
    assert "ord()" not in err



@pytest.mark.parametrize("edit, words", [
    (lambda i: i.update(files="x"), "metadata.yaml: key 'files': expected a list, got 'x'"),
    (lambda i: i.update(duration="x"), "metadata.yaml: key 'duration': expected a mapping, got 'x'"),
    (lambda i: i["topics_with_message_count"].__setitem__(0, "x"),
     "metadata.yaml: key 'topics_with_message_count[0]': expected a mapping, got 'x'"),
    (lambda i: i["topics_with_message_count"][0].update(topic_metadata=[1]),
     "metadata.yaml: key 'topics_with_message_count[0].topic_metadata': expected a mapping, got [1]"),
    (lambda i: i.update(version="x"), "metadata.yaml: key 'version': expected a whole number"),
], ids=["files a string", "duration a string", "topic entry a string", "topic metadata a list", "version a string"])
def test_metadata_keys_of_the_wrong_shape_are_named(tmp_path, capsys, edit, words):
    """A ``files`` that is not a list gave an AttributeError traceback, exit 1 (from rosbags closing its reader);
    the other shapes rosbags' "string indices must be integers" (or its comparison of a string version)."""
    bag = _bag(tmp_path / "bag")
    _edit_metadata(bag, edit)
    code, err = _export(capsys, bag, tmp_path)
    _one_line(code, err, bag, words)
    assert "indices" not in err
