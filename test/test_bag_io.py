"""Bag reading (issue 6): a synthetic rosbag2 written with the rosbags Writer reads back exactly.

The bags here are written with ``rosbags.rosbag2.Writer`` (MCAP, metadata version 9) from known
samples, independently of :class:`mpm_monitor.io.bags.BagWriter`.  Every malformed bag must raise
:class:`BagError` with one line that names the bag and, where it is about one topic, the topic.
"""

import io
import struct

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.core.errors import BagError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io import bags as bag_io
from mpm_monitor.io.bags import BagWriter, export_csv, read_bag, read_bag_channels, read_diagnostics, read_raw_messages
from mpm_monitor.io.bags import read as bag_read
from mpm_monitor.io.csv_log import read_csv
from mpm_monitor.io.model_file import save_model

TS = bag_io.default_typestore()
JS = TS.types["sensor_msgs/msg/JointState"]
HEADER = TS.types["std_msgs/msg/Header"]
TIME = TS.types["builtin_interfaces/msg/Time"]

MODEL = PlantModel(sample_time=0.5, inputs=("u1", "u2"), outputs=("y1", "y2", "y3"),
                   gain=np.ones((3, 2)), time_constant=np.full((3, 2), 5.0), delay=np.zeros((3, 2)))
T0 = 100.0  # stamp of sample 0, seconds


def _joint_state(stamp_ns, names, values):
    return JS(header=HEADER(stamp=TIME(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=""),
              name=list(names), position=np.asarray(values, dtype=np.float64),
              velocity=np.zeros(0, dtype=np.float64), effort=np.zeros(0, dtype=np.float64))


def _samples(n, seed=3):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)), rng.normal(size=(n, 2)), rng.normal(size=(n, 3))


def write_bag(path, r, u, y, *, stamps=None, names=None, skip=(), drop_topics=(), msgtype=None,
              diagnostics=None, again=None, received=None, prefix="/", role_stamps=None, role_received=None):
    """Write r/u/y as /setpoint, /input, /output JointState messages, one sample after the other.

    stamps : (n,) int ns per sample (default T0 + k * TS); names : role -> channel names as sent;
    skip : (role, k) messages left out; drop_topics : roles with no connection at all; again : (role, k) ->
    a number added to the values of a second message for that sample (0: the same message sent again);
    received : (n,) int ns, the recorder's times of the samples (default their stamps); prefix : of the topic
    names ("" stores them relative, as some tools do); role_stamps, role_received : role -> (n,) stamps, recorder's times of that topic alone.
    """
    again = again or {}
    n = len(r)
    stamps = (np.arange(n) * int(MODEL.sample_time * 1e9) + int(T0 * 1e9)) if stamps is None else stamps
    received = stamps if received is None else received
    names = {"setpoint": MODEL.outputs, "input": MODEL.inputs, "output": MODEL.outputs, **(names or {})}
    data = {"setpoint": r, "input": u, "output": y}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for role in ("output", "input", "setpoint"):
            if role not in drop_topics:
                conns[role] = w.add_connection(f"{prefix}{role}", msgtype or JS.__msgtype__, typestore=TS)
        if diagnostics is not None:
            conns["diag"] = w.add_connection("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", typestore=TS)
        for k in range(n):
            for role in ("output", "input", "setpoint"):  # the loop's order: y(k), then u(k)
                if role in conns and (role, k) not in skip:
                    want = list(names[role])
                    base = list(MODEL.outputs if role != "input" else MODEL.inputs)
                    vals = [data[role][k][base.index(c)] if c in base else 7.0 for c in want]
                    msg = _joint_state(int((role_stamps or {}).get(role, stamps)[k]), want, vals)
                    at = (role_received or {}).get(role, received)[k]
                    w.write(conns[role], int(at) + 1000, TS.serialize_cdr(msg, JS.__msgtype__))
                    if (role, k) in again:
                        msg = _joint_state(int(stamps[k]), want, np.asarray(vals) + again[(role, k)])
                        w.write(conns[role], int(received[k]) + 2000, TS.serialize_cdr(msg, JS.__msgtype__))
        for t_ns, arr in diagnostics or ():
            w.write(conns["diag"], t_ns, TS.serialize_cdr(arr, "diagnostic_msgs/msg/DiagnosticArray"))
    return path


def test_round_trip_exact(tmp_path):
    r, u, y = _samples(40)
    bag = write_bag(tmp_path / "bag", r, u, y)
    data = read_bag(bag, MODEL)
    np.testing.assert_array_equal(data.r, r)
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_array_equal(data.y, y)
    np.testing.assert_allclose(data.t, T0 + 0.5 * np.arange(40), rtol=0, atol=1e-9)
    assert data.inputs == MODEL.inputs and data.outputs == MODEL.outputs and data.sample_time == 0.5


def test_a_bag_that_stores_relative_topic_names_is_read(tmp_path):
    """A bag whose topics are stored as 'setpoint', 'input', 'output' (no leading slash) was refused, "no topic
    '/setpoint' ... topics in the bag: input, output, setpoint", whatever --topics said."""
    r, u, y = _samples(20)
    bag = write_bag(tmp_path / "bag", r, u, y, prefix="")
    for topics in (("setpoint", "input", "output"), ("/setpoint", "/input", "/output")):
        data = read_bag(bag, MODEL, topics)
        np.testing.assert_array_equal(data.u, u)
        np.testing.assert_array_equal(data.y, y)
    assert {m.topic for m in read_raw_messages(bag, ["input"])} == {"input"}
    export_csv(bag, tmp_path / "rel.csv")
    export_csv(write_bag(tmp_path / "abs", r, u, y), tmp_path / "abs.csv")
    assert (tmp_path / "rel.csv").read_text() == (tmp_path / "abs.csv").read_text()


def test_channels_matched_by_name_extra_ignored(tmp_path):
    r, u, y = _samples(10)
    bag = write_bag(tmp_path / "bag", r, u, y, names={"input": ("u2", "extra", "u1"), "output": ("y3", "y1", "y2")})
    data = read_bag(bag, MODEL)
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_array_equal(data.y, y)


def test_partial_first_and_last_samples_are_trimmed(tmp_path):
    r, u, y = _samples(12)
    # recording started after y(0) went out and stopped after y(11) but before u(11), r(11)
    bag = write_bag(tmp_path / "bag", r, u, y, skip={("output", 0), ("input", 11), ("setpoint", 11)})
    data = read_bag(bag, MODEL)
    assert data.n_samples == 10
    np.testing.assert_array_equal(data.y, y[1:11])
    np.testing.assert_array_equal(data.u, u[1:11])
    assert data.t[0] == pytest.approx(T0 + 0.5)


def test_export_csv_equals_read_bag(tmp_path):
    r, u, y = _samples(25)
    bag = write_bag(tmp_path / "bag", r, u, y)
    model_file = tmp_path / "model.yaml"
    save_model(MODEL, model_file)
    for name, model_path in (("with.csv", model_file), ("without.csv", None)):
        n = export_csv(bag, tmp_path / name, model_path=model_path)
        assert n == 25
        data = read_csv(tmp_path / name, MODEL)
        np.testing.assert_array_equal(data.r, r)
        np.testing.assert_array_equal(data.u, u)
        np.testing.assert_array_equal(data.y, y)
    guessed = read_bag_channels(bag)
    assert guessed.sample_time == pytest.approx(0.5) and guessed.inputs == ("u1", "u2")


def test_a_bag_of_setpoints_sent_on_change_is_read_with_hold_setpoint(tmp_path, capsys):
    """A stack that publishes its setpoints only on change (the live monitor's hold_setpoint): without a hold, every
    sample without a setpoint message was a gap (an outside check: 433 gaps, a result unlike the live one, and no
    way to get the live one back).  With --hold-setpoint each sample takes the latest setpoint stamped at or before
    it, off the grid or not; the samples before the first are left out, with a note."""
    n = 30
    r, u, y = _samples(n)
    r[:] = 1.0
    r[12:] = 2.0
    r[21:, 1] = -3.0
    sent = [k for k in range(3, n) if k == 3 or np.any(r[k] != r[k - 1])]      # the first setpoint at sample 3
    skip = {("setpoint", k) for k in range(n) if k not in sent}
    stamps = np.arange(n) * int(MODEL.sample_time * 1e9) + int(T0 * 1e9)
    sp_stamps = stamps.copy()
    sp_stamps[21] -= int(0.3 * MODEL.sample_time * 1e9)         # stamped 0.3 sample before its sample: off the grid
    bag = write_bag(tmp_path / "bag", r, u, y, skip=skip, role_stamps={"setpoint": sp_stamps})
    with pytest.raises(BagError, match="off the sample grid"):      # without the hold: aligned by stamp
        read_bag(bag, MODEL)
    data = read_bag(bag, MODEL, hold_setpoint=True)
    np.testing.assert_array_equal(data.r, r[3:])
    np.testing.assert_array_equal(data.u, u[3:])
    np.testing.assert_array_equal(data.y, y[3:])
    assert len(data.segments) == 1 and any("3 samples before its first message" in note for note in data.notes)
    model_file = tmp_path / "model.yaml"
    save_model(MODEL, model_file)
    for name, model_path in (("with.csv", model_file), ("without.csv", None)):
        assert export_csv(bag, tmp_path / name, model_path=model_path, hold_setpoint=True) == n - 3
        np.testing.assert_array_equal(read_csv(tmp_path / name, MODEL).r, r[3:])
    assert cli_main(["export", "--bag", str(bag), "--csv", str(tmp_path / "x.csv"), "--hold-setpoint"]) == 0
    assert "wrote 27 samples" in capsys.readouterr().out
    # A CSV has a setpoint in every row: the flag is refused with --data.
    assert cli_main(["analyze", "--model", str(model_file), "--data", str(tmp_path / "x.csv"), "--hold-setpoint"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--hold-setpoint" in err and "--bag" in err


def test_cli_export(tmp_path, capsys):
    r, u, y = _samples(8)
    bag = write_bag(tmp_path / "bag", r, u, y)
    assert cli_main(["export", "--bag", str(bag), "--csv", str(tmp_path / "x.csv")]) == 0
    assert "wrote 8 samples" in capsys.readouterr().out
    assert cli_main(["export", "--bag", str(tmp_path / "nothing"), "--csv", str(tmp_path / "y.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such bag directory" in err


def test_progress_bar_on_long_bags(tmp_path, monkeypatch):
    r, u, y = _samples(300)
    bag = write_bag(tmp_path / "bag", r, u, y)
    stream = io.StringIO()
    read_bag(bag, MODEL, progress=stream)
    assert stream.getvalue() == ""  # short bag: no bar
    monkeypatch.setattr(bag_read, "LONG_BAG_MESSAGES", 500)
    read_bag(bag, MODEL, progress=stream)
    assert "100%" in stream.getvalue() and "900/900 messages" in stream.getvalue()


def _diagnostic_arrays(n: int) -> list:
    """``n`` (log time, DiagnosticArray) of two row statuses each."""
    status_t = TS.types["diagnostic_msgs/msg/DiagnosticStatus"]
    kv_t = TS.types["diagnostic_msgs/msg/KeyValue"]
    arr_t = TS.types["diagnostic_msgs/msg/DiagnosticArray"]
    arrays = []
    for k in range(n):
        st = [status_t(level=k % 2, name=f"mpm_monitor: row y{i}", message="m", hardware_id="h",
                       values=[kv_t(key="rsi", value=f"{k + i}")]) for i in (1, 2)]
        arrays.append((int(T0 * 1e9) + k, arr_t(header=HEADER(stamp=TIME(sec=k, nanosec=0), frame_id=""), status=st)))
    return arrays


def test_read_diagnostics_in_order(tmp_path):
    r, u, y = _samples(3)
    bag = write_bag(tmp_path / "bag", r, u, y, diagnostics=_diagnostic_arrays(3))
    got = read_diagnostics(bag)
    assert [(s.stamp, s.name, s.level, s.values["rsi"]) for s in got] == [
        (float(k), f"mpm_monitor: row y{i}", k % 2, f"{k + i}") for k in range(3) for i in (1, 2)]


def test_live_located_elements_takes_the_last_row_status():
    def st(name, **values):
        return bag_io.RecordedStatus(0.0, 0, name, 1, "", "", values)

    got = bag_io.live_located_elements([
        st("mpm_monitor: row y1", mismatch="true", flagged_inputs="u1"),
        st("mpm_monitor: row y1", mismatch="true", flagged_inputs="u2, u3"),
        st("mpm_monitor: row y2", mismatch="false", flagged_inputs=""),
        st("mpm_monitor: summary", mismatch="true")])
    assert got == {"rows": {"y1": True, "y2": False}, "located": {("y1", "u2"), ("y1", "u3")}}


def test_bag_writer_flush_and_close(tmp_path):
    r, u, y = _samples(3)
    src = write_bag(tmp_path / "src", r, u, y)
    raw = read_raw_messages(src, ["setpoint", "input", "output"])
    w = BagWriter(tmp_path / "copy")
    mcap = tmp_path / "copy" / "copy.mcap"
    for m in raw:
        if not w.has_topic(m.topic):
            w.add_topic(m.topic, m.msgtype)
        w.write(m.topic, m.log_time, m.data)
    size_before = mcap.stat().st_size
    assert w.flush() == len(raw)
    assert mcap.stat().st_size > size_before  # the chunk is on disk before close
    w.close()
    w.close()  # idempotent
    data = read_bag(tmp_path / "copy", MODEL)
    np.testing.assert_array_equal(data.y, y)
    with pytest.raises(BagError, match="exists already"):
        BagWriter(tmp_path / "copy")


def _rewritten(raw, path, flush_after=None):
    """The messages ``raw`` written again by BagWriter into the bag ``path``, closed (every chunk with its
    CRC); flushed after message ``flush_after`` too (two chunks).  Returns the closed writer."""
    w = BagWriter(path, fsync=False)
    for k, m in enumerate(raw):
        if not w.has_topic(m.topic):
            w.add_topic(m.topic, m.msgtype)
        w.write(m.topic, m.log_time, m.data)
        if k == flush_after:
            w.flush()
    w.close()
    return w


def test_bag_writer_gives_every_chunk_its_crc(tmp_path):
    """rosbags' writer leaves the chunk CRC at 0 (unchecked): a flipped bit in a value reads as a wrong
    value.  BagWriter's bags carry the CRC, so rosbags' reader (which checks it) refuses the chunk."""
    r, u, y = _samples(40)
    raw = read_raw_messages(write_bag(tmp_path / "src", r, u, y), ["setpoint", "input", "output"])
    _rewritten(raw, tmp_path / "copy", flush_after=60)   # two chunks: one flushed, one written at close
    np.testing.assert_array_equal(read_bag(tmp_path / "copy", MODEL).y, y)   # rosbags checked the CRCs
    value = struct.pack("<d", y[20, 1])
    for bag, refused in ((tmp_path / "src", False), (tmp_path / "copy", True)):
        mcap = bag / f"{bag.name}.mcap"
        data = mcap.read_bytes()
        assert data.count(value) == 1
        mcap.write_bytes(data.replace(value, struct.pack("<d", y[20, 1] + 1.0)))
        if refused:
            with pytest.raises(BagError) as e:
                read_bag(bag, MODEL)
            _check(e, str(bag), "cannot read bag: Chunk checksum mismatch", "the storage file is damaged")
        else:
            assert read_bag(bag, MODEL).y[20, 1] == y[20, 1] + 1.0   # read as it is, without the CRC


def test_recover_unclosed_bag(tmp_path):
    """A writer that dies after a flush: the flushed messages come back, a torn tail is dropped."""
    import shutil

    r, u, y = _samples(30)
    raw = read_raw_messages(write_bag(tmp_path / "src", r, u, y), ["setpoint", "input", "output"])
    w = BagWriter(tmp_path / "live")
    for m in raw[:60]:
        if not w.has_topic(m.topic):
            w.add_topic(m.topic, m.msgtype, [bag_io.contract_vector_qos()])
        w.write(m.topic, m.log_time, m.data)
    w.flush()
    for m in raw[60:]:
        w.write(m.topic, m.log_time, m.data)  # not flushed: still in memory when the process dies
    (tmp_path / "dead").mkdir()
    shutil.copy(tmp_path / "live" / "live.mcap", tmp_path / "dead" / "dead.mcap")
    with open(tmp_path / "dead" / "dead.mcap", "ab") as fh:
        fh.write(b"\x06" + (10**6).to_bytes(8, "little") + b"torn")  # a chunk cut short by the kill
    w.close()
    with pytest.raises(BagError, match="no metadata.yaml"):
        read_bag(tmp_path / "dead", MODEL)
    notes = []
    assert bag_io.recover_bag(tmp_path / "dead", tmp_path / "back", warn=notes.append) == 60
    back = read_raw_messages(tmp_path / "back", ["setpoint", "input", "output"])
    assert [(m.topic, m.log_time, m.data) for m in back] == [(m.topic, m.log_time, m.data) for m in raw[:60]]
    # The torn tail is said (it was dropped without a word).
    assert notes == [f"{tmp_path / 'dead' / 'dead.mcap'}: the storage file is damaged: left out the last 13 bytes of "
                     f"dead.mcap, a record cut short (the messages it held are lost)"]
    import yaml

    meta = yaml.safe_load((tmp_path / "back" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["topics_with_message_count"][0]["topic_metadata"]["offered_qos_profiles"][0]["depth"] == 1000


def _records_of(data: bytes):
    """``(opcode, body start, body)`` of every record of an MCAP file, those inside its chunks too (their
    body start counted in the file; the chunks are checked to be uncompressed)."""
    from mpm_monitor.io.bags.mcap_records import CHUNK, MAGIC, mcap_records, mcap_string

    for op, start, body in mcap_records(data, len(MAGIC), len(data)):
        yield op, start, body
        if op == CHUNK:
            compression, pos = mcap_string(body, 28)
            assert compression == b""
            (size,) = struct.unpack_from("<Q", body, pos)
            first = start + pos + 8
            yield from mcap_records(data, first, first + size)


def test_recover_leaves_out_a_chunk_whose_crc_does_not_match(tmp_path):
    """A killed recording whose storage file was also damaged: the chunk whose bytes no longer match its
    CRC is left out, said in one warning, and the other chunk's messages come back."""
    import shutil

    r, u, y = _samples(40)
    raw = read_raw_messages(write_bag(tmp_path / "src", r, u, y), ["setpoint", "input", "output"])
    _rewritten(raw, tmp_path / "live", flush_after=59)   # chunk 1: samples 0 to 19; chunk 2: 20 to 39
    (tmp_path / "dead").mkdir()
    mcap = tmp_path / "dead" / "dead.mcap"
    shutil.copy(tmp_path / "live" / "live.mcap", mcap)   # no metadata.yaml, as after a kill
    value = struct.pack("<d", y[30, 1])
    data = mcap.read_bytes()
    assert data.count(value) == 1
    mcap.write_bytes(data.replace(value, struct.pack("<d", y[30, 1] + 1.0)))
    notes = []
    assert bag_io.recover_bag(tmp_path / "dead", tmp_path / "back", warn=notes.append) == 60
    assert notes == [f"{mcap}: the storage file is damaged: left out 1 damaged chunk (a CRC, length or "
                     f"compression field that does not match the bytes)"]
    back = read_raw_messages(tmp_path / "back", ["setpoint", "input", "output"])
    assert [(m.topic, m.log_time, m.data) for m in back] == [(m.topic, m.log_time, m.data) for m in raw[:60]]


@pytest.mark.parametrize("closed", [False, True], ids=["killed", "closed"])
def test_recover_with_a_damaged_channel_record(tmp_path, closed):
    """A channel record whose bytes were changed (no CRC: rosbags' writer) cannot be parsed.  In a killed
    recording its messages have no topic or type and are left out, said in one warning, and the other
    topics' come back; a closed file's summary repeats the record, and every message comes back."""
    from mpm_monitor.io.bags.mcap_records import CHANNEL, DATA_END, mcap_string

    r, u, y = _samples(10)
    bag = write_bag(tmp_path / "src", r, u, y)
    raw = read_raw_messages(bag, ["setpoint", "input", "output"])
    data = bytearray((bag / "src.mcap").read_bytes())
    records = list(_records_of(bytes(data)))
    start = next(st for op, st, body in records                      # the data section's, not the summary's
                 if op == CHANNEL and mcap_string(body, 4)[0] == b"/input")
    struct.pack_into("<I", data, start + 4, 2**32 - 1)               # the topic name's length
    if not closed:                                                   # killed: no data end, no summary
        data = data[:next(st for op, st, _ in records if op == DATA_END) - 9]
    (tmp_path / "dead").mkdir()
    (tmp_path / "dead" / "dead.mcap").write_bytes(bytes(data))
    notes = []
    n = bag_io.recover_bag(tmp_path / "dead", tmp_path / "back", warn=notes.append)
    lost = 10 if not closed else 0
    assert n == 30 - lost
    assert notes == [f"{tmp_path / 'dead' / 'dead.mcap'}: the storage file is damaged: left out 1 record that cannot "
                     f"be parsed" + (f", {lost} messages of a channel with no readable channel or schema record"
                                     if lost else "")]
    topics = ["setpoint", "output"] + (["input"] if closed else [])
    back = read_raw_messages(tmp_path / "back", topics)
    assert [(m.topic, m.data) for m in back] == [(m.topic, m.data) for m in raw if closed or m.topic != "/input"]


@pytest.mark.parametrize("name", [b"zstd", b"\x00q\x7f!"], ids=["zstd", "garbage"])
def test_recover_names_compressed_chunks_and_leaves_out_a_garbage_compression(tmp_path, name):
    """A chunk that says it is zstd-compressed cannot be recovered (refused in one line); a compression
    name no writer uses is a damaged chunk, left out."""
    from mpm_monitor.io.bags.mcap_records import CHUNK, mcap_string

    r, u, y = _samples(10)
    data = (write_bag(tmp_path / "src", r, u, y) / "src.mcap").read_bytes()
    start, body = next((st, body) for op, st, body in _records_of(data) if op == CHUNK)
    compression, pos = mcap_string(body, 28)
    assert compression == b""
    body = body[:28] + struct.pack("<I", len(name)) + name + body[pos:]          # the same records, renamed
    (tmp_path / "dead").mkdir()
    mcap = tmp_path / "dead" / "dead.mcap"
    mcap.write_bytes(data[:start - 8] + struct.pack("<Q", len(body)) + body + data[start + len(body) - len(name):])
    notes = []
    if name == b"zstd":
        with pytest.raises(BagError) as e:
            bag_io.recover_bag(tmp_path / "dead", tmp_path / "back", warn=notes.append)
        _check(e, f"{mcap}: compressed chunks (zstd) cannot be recovered")
    else:
        with pytest.raises(BagError) as e:          # the bag's one chunk: nothing is left
            bag_io.recover_bag(tmp_path / "dead", tmp_path / "back", warn=notes.append)
        _check(e, f"{mcap}: no complete message to recover: left out 1 damaged chunk (a CRC, length or "
                  f"compression field that does not match the bytes)")


def test_recover_with_no_complete_message_creates_nothing(tmp_path, capsys):
    """A recording killed before its first chunk reached the disk: one line, and no empty bag."""
    from mpm_monitor.io.bags.mcap_records import MAGIC

    (tmp_path / "dead").mkdir()
    (tmp_path / "dead" / "dead.mcap").write_bytes(MAGIC + b"\x06" + (10**6).to_bytes(8, "little") + b"torn")
    with pytest.raises(BagError) as e:
        bag_io.recover_bag(tmp_path / "dead", tmp_path / "back")
    _check(e, "dead.mcap: no complete message to recover (expected at least one complete chunk of messages")
    assert not (tmp_path / "back").exists()
    assert cli_main(["recover", "--bag", str(tmp_path / "dead"), "--out", str(tmp_path / "back")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "no complete message to recover" in err and "\n" not in err


# --- malformed bags: one line, naming the bag and the topic ------------------------------------------


def _check(exc_info, *words):
    text = str(exc_info.value)
    assert "\n" not in text
    for w in words:
        assert w in text, text


def test_missing_and_empty_dir(tmp_path):
    with pytest.raises(BagError) as e:
        read_bag(tmp_path / "nope", MODEL)
    _check(e, "nope", "no such bag directory")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError) as e:
        read_bag(tmp_path / "empty", MODEL)
    _check(e, "empty", "empty directory")


def test_no_metadata(tmp_path):
    r, u, y = _samples(5)
    bag = write_bag(tmp_path / "bag", r, u, y)
    (bag / "metadata.yaml").unlink()
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "no metadata.yaml")


def test_a_metadata_yaml_that_is_a_directory_or_a_pipe_is_named_so(tmp_path):
    """Not "no metadata.yaml": the entry is there, of the wrong kind (a pipe is never opened: no wait)."""
    import os

    r, u, y = _samples(5)
    for kind, make in (("a directory", os.mkdir), ("a named pipe", os.mkfifo)):
        bag = write_bag(tmp_path / kind.replace(" ", "_"), r, u, y)
        (bag / "metadata.yaml").unlink()
        make(bag / "metadata.yaml")
        with pytest.raises(BagError) as e:
            read_bag(bag, MODEL)
        _check(e, str(bag), f"metadata.yaml is {kind}: expected the YAML file rosbag2 writes")


def test_truncated_mcap(tmp_path):
    r, u, y = _samples(50)
    bag = write_bag(tmp_path / "bag", r, u, y)
    mcap = bag / "bag.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "cannot read bag")
    assert "python -m mpm_monitor recover --bag DIR --out NEW" in str(e.value)      # the command that mends it


def test_garbage_record_length(tmp_path):
    # A record length of 2^50 bytes (a damaged storage file): reading it would ask for a petabyte.
    r, u, y = _samples(50)
    bag = write_bag(tmp_path / "bag", r, u, y)
    mcap = bag / "bag.mcap"
    data = bytearray(mcap.read_bytes())
    footer = len(data) - 8 - 29                     # MCAP: footer record (opcode 2, 20 bytes), then the magic
    assert data[footer] == 0x02
    (summary_start,) = struct.unpack_from("<Q", data, footer + 9)
    struct.pack_into("<Q", data, summary_start + 1, 2**50)   # the summary's first record's length
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "cannot read bag: a record's length runs far past the end of the storage file")
    assert "MemoryError" not in str(e.value)


def _first_message_length_offset(mcap) -> int:
    """Offset of the length field of the first message record of ``mcap`` (inside its first chunk)."""
    from mpm_monitor.io.bags.mcap_records import MESSAGE

    return next(start - 8 for op, start, _ in _records_of(mcap.read_bytes()) if op == MESSAGE)


@pytest.mark.parametrize("length, words", [
    (10**6, ("Truncated record", "(a length field does not match the bytes after it: the storage file is damaged)")),
    (2**64 - 1, ("a record's length runs far past the end of its chunk: the storage file is damaged",)),
], ids=["past the chunk", "past an index"])
@pytest.mark.parametrize("with_model", [True, False], ids=["model", "no model"])
def test_garbage_length_inside_a_chunk(tmp_path, length, words, with_model):
    """A message's length field damaged inside a chunk without CRC (rosbags' writer): the bag opens, and
    reading its messages fails with one line, with or without a model (``export`` reads the channel
    names from the first messages first)."""
    r, u, y = _samples(20)
    bag = write_bag(tmp_path / "bag", r, u, y)
    mcap = bag / "bag.mcap"
    data = bytearray(mcap.read_bytes())
    struct.pack_into("<Q", data, _first_message_length_offset(mcap), length)
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL) if with_model else read_bag_channels(bag)
    _check(e, str(bag), "cannot read bag: ", *words)
    assert "Error" not in str(e.value) and "cannot fit" not in str(e.value)


@pytest.mark.parametrize("topic, read, counted", [
    ("/input", lambda bag: read_bag(bag, MODEL), 5),
    ("/input", read_bag_channels, 5),
    ("/diagnostics", read_diagnostics, 3),
    ("/input", lambda bag: read_raw_messages(bag, ["setpoint", "input", "output"]), 5),
], ids=["model", "no model", "diagnostics", "raw (replay)"])
def test_metadata_that_no_longer_matches_the_storage_file(tmp_path, topic, read, counted):
    """rosbags matches each topic of metadata.yaml to the storage file's channel (QoS profiles
    included): an edited profile leaves the topic counted in the metadata but with no message read."""
    import yaml

    r, u, y = _samples(5)
    bag = write_bag(tmp_path / "bag", r, u, y, diagnostics=_diagnostic_arrays(3))
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    topics = meta["rosbag2_bagfile_information"]["topics_with_message_count"]
    (entry,) = [t for t in topics if t["topic_metadata"]["name"] == topic]
    forever = {"sec": 9223372036, "nsec": 854775807}
    entry["topic_metadata"]["offered_qos_profiles"] = [{
        "history": "keep_last", "depth": 10, "reliability": "reliable", "durability": "volatile",
        "deadline": forever, "lifespan": forever, "liveliness": "automatic",
        "liveliness_lease_duration": forever, "avoid_ros_namespace_conventions": False}]
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(BagError) as e:
        read(bag)
    _check(e, str(bag), f"topic '{topic}': metadata.yaml counts {counted} messages but none could be read from the "
                        f"storage file: expected metadata.yaml as rosbag2 wrote it for this storage file")


def _rename_metadata_key(bag):
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text().replace("serialization_format", "serialisation_format"))


@pytest.mark.parametrize("damage, words", [
    (_rename_metadata_key, ("serialization_format", "(expected metadata.yaml as rosbag2 writes it)")),
    (lambda bag: (bag / "bag.mcap").unlink(), ("bag.mcap", "(expected the storage file metadata.yaml names, beside it)")),
], ids=["metadata key", "storage file"])
def test_what_is_missing_is_named_without_the_truncation_hint(tmp_path, damage, words):
    r, u, y = _samples(5)
    bag = write_bag(tmp_path / "bag", r, u, y)
    damage(bag)
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "cannot read bag", *words)
    assert "truncated" not in str(e.value)


def test_a_type_hash_edited_in_the_metadata_is_named_without_the_truncation_hint(tmp_path):
    """A bag that stores its message definitions (BagWriter's): rosbags checks the type hash the metadata
    records (the last topic's of each type) against the definition's, and a hash edited in metadata.yaml
    is said to disagree with it."""
    r, u, y = _samples(5)
    raw = read_raw_messages(write_bag(tmp_path / "src", r, u, y), ["setpoint", "input", "output"])
    _rewritten(raw, tmp_path / "bag")
    meta = tmp_path / "bag" / "metadata.yaml"
    text = meta.read_text()
    assert text.count("RIHS01_a13ee3a330e346c9") == 3
    head, tail = text.rsplit("RIHS01_a13ee3a330e346c9", 1)      # the last topic's: rosbags checks that one
    meta.write_text(head + "RIHS01_a13ee3a330e346c8" + tail)
    with pytest.raises(BagError) as e:
        read_bag(tmp_path / "bag", MODEL)
    _check(e, str(tmp_path / "bag"), "cannot read bag: Message type 'sensor_msgs/msg/JointState' hash mismatch",
           "(the message definition stored in the bag and the type hash recorded for it disagree: expected "
           "metadata.yaml and the storage file as rosbag2 wrote them)")
    assert "truncated" not in str(e.value)


def test_missing_topic(tmp_path):
    r, u, y = _samples(5)
    bag = write_bag(tmp_path / "bag", r, u, y, drop_topics=("input",))
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "no topic '/input'", "/output")


def test_wrong_type(tmp_path):
    r, u, y = _samples(2)
    bag = tmp_path / "bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for role in ("setpoint", "input", "output"):
            w.add_connection(f"/{role}", "std_msgs/msg/Float64MultiArray", typestore=TS)
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, "'/setpoint'", "std_msgs/msg/Float64MultiArray", "expected sensor_msgs/msg/JointState")


@pytest.mark.parametrize("role, what", [("input", "inputs"), ("output", "outputs")])
def test_a_topic_without_channel_names_is_refused_without_a_model(tmp_path, capsys, role, what):
    """Without a model the first message names the channels: an empty name list is refused (it used to
    export a CSV without those columns), as it is against the model's names."""
    r, u, y = _samples(6)
    names = {"input": ()} if role == "input" else {"output": (), "setpoint": ()}
    bag = write_bag(tmp_path / "bag", r, u, y, names=names)
    for read in (lambda: read_bag_channels(bag), lambda: export_csv(bag, tmp_path / "x.csv")):
        with pytest.raises(BagError) as e:
            read()
        _check(e, str(bag), f"'/{role}'", "names no channel", f"the {what} are named by the first message",
               "--model")
    assert not (tmp_path / "x.csv").exists()
    assert cli_main(["export", "--bag", str(bag), "--csv", str(tmp_path / "y.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "names no channel" in err and not (tmp_path / "y.csv").exists()
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, f"'/{role}'", "has channel names []")


def test_wrong_channel_names(tmp_path):
    r, u, y = _samples(5)
    bag = write_bag(tmp_path / "bag", r, u, y, names={"input": ("u1", "uX")})
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "'/input'", "[u1, uX]", "expected the inputs [u1, u2]")


def test_gap(tmp_path):
    # Until the interface "Gaps" a gap was refused; the bag now reads as data with gaps, as a CSV does.
    r, u, y = _samples(20)
    bag = write_bag(tmp_path / "bag", r, u, y, skip={("output", 7), ("output", 8), ("input", 12)})
    data = read_bag(bag, MODEL)
    kept = [k for k in range(20) if k not in (7, 8, 12)]
    np.testing.assert_array_equal(data.grid_index, kept)
    assert data.segments == [(0, 7), (7, 10), (10, 17)]
    np.testing.assert_allclose(data.t[7] - data.t[6], 1.5)              # 0.5 s samples: 7 and 8 missing
    np.testing.assert_array_equal(data.u, u[kept])
    np.testing.assert_array_equal(data.y, y[kept])
    np.testing.assert_array_equal(data.r, r[kept])


def test_duplicate_stamp(tmp_path):
    r, u, y = _samples(6)
    stamps = np.arange(6) * 500_000_000 + 10**11
    stamps[3] = stamps[2]
    bag = write_bag(tmp_path / "bag", r, u, y, stamps=stamps)
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "'/setpoint'", "duplicate stamp", "two different messages stamped 101 s")
    # A clock stepped back by a few samples (within those put in order) makes duplicates too: it is named.
    received = np.arange(12) * 500_000_000 + 10**11
    stamps = received.copy()
    stamps[6:] -= 1_500_000_000
    bag = write_bag(tmp_path / "back", *_samples(12), stamps=stamps, received=received)
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, "'/setpoint'", "two different messages stamped 101.5 s", "message 7's stamp 101.5 s goes back 1 s",
           "a clock stepped back?")


def test_off_grid_stamp(tmp_path):
    r, u, y = _samples(6)
    stamps = np.arange(6) * 500_000_000 + 10**11
    stamps[4] += 200_000_000  # 0.4 of a sample late
    bag = write_bag(tmp_path / "bag", r, u, y, stamps=stamps)
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "'/setpoint'", "stamp 102.2 s is off the sample grid")


def test_stamps_the_live_monitor_takes_are_read(tmp_path):
    """Stamps jittered by up to 0.2 of a sample (within the monitor's default stamp_tolerance 0.25, so a
    recording of a stream it analysed) are placed on their samples."""
    from mpm_monitor.monitor.window import WindowOptions

    assert bag_read.GRID_TOLERANCE == WindowOptions().stamp_tolerance
    r, u, y = _samples(8)
    jitter = np.array([0, 0.2, -0.2, 0.15, -0.1, 0.2, 0, -0.2]) * 500_000_000
    stamps = np.arange(8) * 500_000_000 + 10**11 + jitter.astype(np.int64)
    data = read_bag(write_bag(tmp_path / "bag", r, u, y, stamps=stamps), MODEL)
    np.testing.assert_array_equal(data.t, 100.0 + np.arange(8) * 0.5)
    np.testing.assert_array_equal(data.y, y)


def test_a_stamp_from_before_the_clock_was_set_is_left_out_with_a_note(tmp_path, capsys):
    """Every topic's first message stamped 0 (the clock not yet set, or a publisher that never fills
    the stamp), the rest on the wall clock: those messages cannot be placed on the grid, so they are
    left out and said, not read as a sample 1.7e9 s before the others (a 3.4e9-sample gap)."""
    r, u, y = _samples(300)
    wall = 1_700_000_000 * 10**9
    stamps = np.concatenate([[0], wall + np.arange(299) * int(MODEL.sample_time * 1e9)])
    bag = write_bag(tmp_path / "bag", r, u, y, stamps=stamps)
    data = read_bag(bag, MODEL)
    assert data.n_samples == 299 and data.segments == [(0, 299)]
    np.testing.assert_array_equal(data.y, y[1:])
    assert data.t[0] == pytest.approx(wall / 1e9)
    assert len(data.notes) == 3
    assert all(n.startswith(f"{bag}: topic '/") and "1 message of 300 with an unset header.stamp (0" in n
               for n in data.notes)
    # The note leads the report's warnings, and the export says it too.
    model_file = tmp_path / "model.yaml"
    save_model(MODEL, model_file)
    from mpm_monitor.core.analysis import AnalysisOptions, detect

    report = detect(MODEL, data, AnalysisOptions(na=1, nb=2, repair=False, element_response=False))
    assert report.warnings[:3] == list(data.notes) and report.gaps is None
    assert cli_main(["export", "--bag", str(bag), "--csv", str(tmp_path / "x.csv"), "--model", str(model_file)]) == 0
    out = capsys.readouterr()
    assert "wrote 299 samples" in out.out and out.err.count("unset header.stamp") == 3


def test_an_unset_stamp_in_the_middle_is_a_gap(tmp_path):
    r, u, y = _samples(40)
    stamps = 1_700_000_000 * 10**9 + np.arange(40) * int(MODEL.sample_time * 1e9)
    stamps[17] = 0
    bag = write_bag(tmp_path / "bag", r, u, y, stamps=stamps)
    data = read_bag(bag, MODEL)
    assert data.segments == [(0, 17), (17, 39)]
    np.testing.assert_array_equal(data.u, np.delete(u, 17, axis=0))
    assert len(data.notes) == 3


def test_a_bag_on_simulated_time_keeps_its_sample_at_zero(tmp_path):
    r, u, y = _samples(12)
    stamps = np.arange(12) * int(MODEL.sample_time * 1e9)   # sim time from 0: stamp 0 is a real sample
    bag = write_bag(tmp_path / "bag", r, u, y, stamps=stamps)
    data = read_bag(bag, MODEL)
    assert data.n_samples == 12 and data.notes == ()
    np.testing.assert_array_equal(data.y, y)


def test_a_topic_whose_stamps_are_all_unset_is_refused(tmp_path):
    r, u, y = _samples(6)
    bag = write_bag(tmp_path / "bag", r, u, y, stamps=np.zeros(6, dtype=np.int64))
    with pytest.raises(BagError) as e:
        read_bag(bag, MODEL)
    _check(e, str(bag), "every message has an unset header.stamp (0)", "fill in header.stamp")


def test_a_bag_whose_crcs_cannot_be_written_is_still_closed(tmp_path, monkeypatch):
    from mpm_monitor.io.bags import write as bag_write

    def fail(path, fsync=False):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(bag_write, "write_chunk_crcs", fail)
    r, u, y = _samples(5)
    raw = read_raw_messages(write_bag(tmp_path / "src", r, u, y), ["setpoint", "input", "output"])
    w = _rewritten(raw, tmp_path / "copy")
    assert w.crc_error.endswith("copy.mcap: chunk CRCs not written: [Errno 28] No space left on device")
    np.testing.assert_array_equal(read_bag(tmp_path / "copy", MODEL).y, y)


def test_a_message_sent_again_for_a_sample_is_kept_once_and_two_different_ones_refused(tmp_path):
    """The plant node re-sends y(k) after a lock-step stall and the recorder records both: the bag was refused
    ("duplicate stamp") while the live monitor keeps one copy.  The same values are now kept once, with a note;
    two different vectors for one sample are still refused."""
    r, u, y = _samples(30)
    data = read_bag(write_bag(tmp_path / "same", r, u, y, again={("output", 12): 0.0}), MODEL)
    np.testing.assert_array_equal(data.y, y)
    assert data.n_samples == 30 and any("1 message sent again for a sample (the same values) kept once" in n
                                        for n in data.notes)
    with pytest.raises(BagError, match=r"topic '/output': duplicate stamp: two different messages stamped"):
        read_bag(write_bag(tmp_path / "other", r, u, y, again={("output", 12): 0.5}), MODEL)


def test_a_clock_that_steps_back_is_refused_and_a_few_samples_out_of_order_are_sorted(tmp_path):
    """Stamps that jumped back by hours were sorted silently (the data recorded later came first in the log)."""
    r, u, y = _samples(40)
    ts = int(MODEL.sample_time * 1e9)
    stamps = np.arange(40) * ts + int(T0 * 1e9)
    back = stamps.copy()
    back[20:] -= 50 * 10**9
    with pytest.raises(BagError, match=r"topic '/setpoint': message 21's stamp 60 s goes back 49.5 s from the stamp "
                                       r"before it \(109.5 s\): expected stamps that increase"):
        read_bag(write_bag(tmp_path / "back", r, u, y, stamps=back, received=stamps), MODEL)
    swapped = stamps.copy()
    swapped[[20, 21]] = swapped[[21, 20]]               # two samples delivered out of order: put in order
    data = read_bag(write_bag(tmp_path / "swap", r, u, y, stamps=swapped, received=stamps), MODEL)
    order = np.arange(40)
    order[[20, 21]] = order[[21, 20]]
    np.testing.assert_array_equal(data.y, y[order])


def test_a_topic_whose_clock_runs_ahead_of_the_others_is_refused(tmp_path):
    """The output's stamps jumped 5 s (10 samples) forward halfway while the recorder's times ran on: the bag was
    read with y(k) paired with u(k + 10) and r(k + 10) for the whole second half, said as a gap of 10 samples.
    Its messages are recorded well before the other topics' messages of the same sample: refused.  A topic
    delivered late for a while (a stall, then caught up) is no sign of it."""
    r, u, y = _samples(240)
    ts = int(MODEL.sample_time * 1e9)
    stamps = np.arange(240) * ts + int(T0 * 1e9)
    jumped = stamps.copy()
    jumped[120:] += 5 * 10**9
    with pytest.raises(BagError) as e:
        read_bag(write_bag(tmp_path / "jump", r, u, y, role_stamps={"output": jumped}, received=stamps), MODEL)
    _check(e, "topic '/output': from its sample at 165 s on, its messages are recorded about 10 samples (5 s) "
              "before the other topics'", "a clock that jumped forward")
    with pytest.raises(BagError, match="topic '/input': from its sample at"):       # a publisher's clock set apart
        read_bag(write_bag(tmp_path / "apart", r, u, y, role_stamps={"input": stamps + 5 * 10**9}, received=stamps),
                 MODEL)
    late = stamps.copy()
    late[100:160] = stamps[160]                          # the output held up for 30 s, then delivered at once
    data = read_bag(write_bag(tmp_path / "late", r, u, y, received=stamps, role_received={"output": late}), MODEL)
    np.testing.assert_array_equal(data.y, y)
    assert [n for n in data.notes if "recorded about" in n and "after the other topics'" in n]    # named, kept


def test_a_topic_recorded_well_after_the_others_is_named_and_kept(tmp_path):
    """The input's stamps run 5 s (10 samples) behind the loop's time: its messages are recorded 10 samples after
    the others' of the same sample.  That is also what a delivery held up 5 s looks like, so the bag is read as
    stamped, with a note naming the topic (before: nothing)."""
    r, u, y = _samples(240)
    ts = int(MODEL.sample_time * 1e9)
    stamps = np.arange(240) * ts + int(T0 * 1e9)
    data = read_bag(write_bag(tmp_path / "behind", r, u, y, role_stamps={"input": stamps - 5 * 10**9}, received=stamps),
                    MODEL)
    notes = [n for n in data.notes if "recorded about" in n]
    assert len(notes) == 1 and "topic '/input': from about its sample at" in notes[0], data.notes
    assert "about 10 samples (5 s) after the other topics' messages of the same sample" in notes[0]
    assert "kept as stamped" in notes[0] and "\n" not in notes[0]
    assert not [n for n in read_bag(write_bag(tmp_path / "fine", r, u, y), MODEL).notes if "recorded about" in n]


def test_a_late_message_stamped_0_in_simulated_time_is_a_step_back(tmp_path):
    """In a bag in simulated time (stamps from 0 s) a message stamped 0 recorded at sample 30 was put on the first
    sample without a word (stamp 0 was taken for an unset stamp, left out of the check for a clock stepped back,
    while a stamp of 1 s was refused)."""
    r, u, y = _samples(40)
    ts = int(MODEL.sample_time * 1e9)
    stamps = np.arange(40) * ts
    sent = stamps.copy()
    sent[31] = 0
    with pytest.raises(BagError, match=r"topic '/setpoint': message 32's stamp 0 s goes back 15 s"):
        read_bag(write_bag(tmp_path / "zero", r, u, y, role_stamps={"setpoint": sent}, received=stamps + 10**9), MODEL)


def test_samples_outside_the_span_every_topic_covers_are_named(tmp_path):
    """One topic recorded 30 samples longer than the others: they were left out without a word."""
    r, u, y = _samples(60)
    skip = {(role, k) for role in ("input", "setpoint") for k in range(30, 60)}
    data = read_bag(write_bag(tmp_path / "bag", r, u, y, skip=skip), MODEL)
    assert data.n_samples == 30
    assert any("topic '/output': 30 of its 60 samples lie outside the span every topic covers" in n for n in data.notes)
    short = read_bag(write_bag(tmp_path / "short", r, u, y, skip={("output", 0)}), MODEL)   # one: no note
    assert not short.notes


def test_fewer_messages_read_than_the_metadata_counts_is_refused(tmp_path):
    """A bit flipped in the storage file's index (its chunk times, which no CRC covers) made the reader skip
    chunks: 168 of 1,500 samples exported with exit 0.  The counts of metadata.yaml are now checked."""
    r, u, y = _samples(30)
    bag = write_bag(tmp_path / "bag", r, u, y)
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    assert "message_count: 30" in text
    meta.write_text(text.replace("message_count: 30", "message_count: 45", 1))
    with pytest.raises(BagError, match=r"metadata.yaml counts 45 messages, 30 could be read from the storage file: the "
                                       r"storage file is damaged \(python -m mpm_monitor recover"):
        read_bag(bag, MODEL)


def test_recover_reads_every_storage_file_of_a_split_recording(tmp_path):
    """A recorder that split its recording (bag_0.mcap, bag_1.mcap, ...) and was then killed: only the first
    file was read (half the samples, exit 0, no warning).  A directory named like a storage file is not one
    (it was an IsADirectoryError traceback)."""
    r, u, y = _samples(40)
    raw = read_raw_messages(write_bag(tmp_path / "src", r, u, y), ["setpoint", "input", "output"])
    (tmp_path / "dead").mkdir()
    for part, msgs in enumerate((raw[:50], raw[50:100], raw[100:])):
        w = BagWriter(tmp_path / f"part{part}")
        for m in msgs:
            if not w.has_topic(m.topic):
                w.add_topic(m.topic, m.msgtype, [bag_io.contract_vector_qos()])
            w.write(m.topic, m.log_time, m.data)
        w.close()
        (tmp_path / f"part{part}" / f"part{part}.mcap").rename(tmp_path / "dead" / f"dead_{[0, 1, 10][part]}.mcap")
    (tmp_path / "dead" / "stray.mcap").mkdir()
    assert bag_io.recover_bag(tmp_path / "dead", tmp_path / "back") == 120
    back = read_raw_messages(tmp_path / "back", ["setpoint", "input", "output"])
    assert [(m.topic, m.log_time, m.data) for m in back] == [(m.topic, m.log_time, m.data) for m in raw]


def test_a_wall_clock_stamp_is_printed_with_every_digit(tmp_path):
    """``%g`` printed a wall-clock stamp as 1.7e+09 s, which no longer located the message."""
    r, u, y = _samples(10)
    y[2, 0] = np.nan
    stamps = np.arange(10) * 500_000_000 + 1_700_000_000 * 10**9 + 250_000_000
    with pytest.raises(BagError, match=r"topic '/output': message 3 \(stamp 1700000001.25 s\) holds a non-finite value"):
        read_bag(write_bag(tmp_path / "bag", r, u, y, stamps=stamps), MODEL)


def test_an_unset_stamp_among_wall_clock_stamps_is_left_out_not_taken_for_a_clock_stepping_back(tmp_path):
    """A message stamped 0 in the middle of wall-clock stamps is left out with a note, as before the check of
    stamps that step back (which must not read the 0 as a step back of 1.7e9 s)."""
    r, u, y = _samples(30)
    stamps = np.arange(30) * 500_000_000 + 1_700_000_000 * 10**9
    sent = stamps.copy()
    sent[12] = 0
    data = read_bag(write_bag(tmp_path / "bag", r, u, y, stamps=sent, received=stamps), MODEL)
    assert data.n_samples == 29 and any("unset header.stamp" in n for n in data.notes)


def test_stamps_within_a_quarter_sample_of_their_samples_are_placed_whatever_the_first_one(tmp_path):
    """The grid was anchored on the earliest stamp: a first output stamp 0.2 sample early and an input stamp 0.2
    late, both within the quarter sample the docs allow, lay 0.4 sample apart and the bag was refused."""
    r, u, y = _samples(40)
    ts = int(MODEL.sample_time * 1e9)
    stamps = np.arange(40) * ts + int(T0 * 1e9)
    early = stamps.copy()
    early[0] -= ts // 5
    late = stamps.copy()
    late[7] += ts // 5
    path = tmp_path / "bag"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {role: w.add_connection(f"/{role}", JS.__msgtype__, typestore=TS) for role in ("output", "input", "setpoint")}
        for k in range(40):
            for role, values, st in (("output", y, early), ("input", u, late), ("setpoint", r, stamps)):
                names = MODEL.inputs if role == "input" else MODEL.outputs
                w.write(conns[role], int(stamps[k]) + 1000,
                        TS.serialize_cdr(_joint_state(int(st[k]), names, values[k]), JS.__msgtype__))
    data = read_bag(path, MODEL)
    assert data.n_samples == 40
    np.testing.assert_array_equal(data.y, y)
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_allclose(data.t, T0 + 0.5 * np.arange(40), rtol=0, atol=1e-9)


def test_the_inferred_sample_time_takes_the_whole_span_not_the_median_jittered_step():
    """Without a model the sample time was the median of the jittered steps (0.999979 s for 1 s), and ``t`` drifted
    by a whole sample over a long bag; a gap does not move it either."""
    rng = np.random.default_rng(5)
    k = np.delete(np.arange(5000), np.arange(2000, 2040))
    stamps = (k * 10**9 + rng.integers(-200_000_000, 200_000_000, size=k.size)).astype(np.int64)
    stamps[0], stamps[-1] = 0, 4999 * 10**9
    # Over the 5,000 samples the estimate drifts by less than a twentieth of a sample; the median alone by more
    # than one.
    assert 5000 * abs(bag_read.infer_sample_time("bag", stamps, "/output") - 1.0) < 0.05
    assert 5000 * abs(float(np.median(np.diff(stamps))) / 1e9 - 1.0) > 1.0
    exact = np.delete(np.arange(300), [7, 8]) * 250_000_000                    # on the grid: the step, exactly
    assert bag_read.infer_sample_time("bag", exact, "/output") == 0.25


def test_recover_holds_about_one_chunk_in_memory_not_the_recording(tmp_path):
    """``recover`` read each storage file whole and kept every message before writing the first: a 30 MB
    recording took 61 MB of Python memory, so a day's recording beside a stack could not be recovered on the
    machine that made it.  Its files are now mapped and each message written as it is read: the peak is that
    of a chunk or two (2 MB chunks here), and every message comes back in order."""
    import shutil
    import tracemalloc

    from mpm_monitor.io.bags.write import joint_state_cdr

    names = [f"j{k}" for k in range(2000)]              # about 40 kB a message
    w = BagWriter(tmp_path / "live", fsync=False)
    w.add_topic("/output", JS.__msgtype__)
    sent = []
    for k in range(750):
        sent.append((k * 10**8, joint_state_cdr(TS, k * 10**8, names, np.full(2000, float(k)))))
        w.write("/output", *sent[-1])
        if k % 50 == 49:
            w.flush()
    (tmp_path / "dead").mkdir()
    shutil.copy(tmp_path / "live" / "live.mcap", tmp_path / "dead" / "dead.mcap")   # killed: no summary, no metadata
    w.close()
    size = (tmp_path / "dead" / "dead.mcap").stat().st_size
    assert size > 29e6
    tracemalloc.start()
    try:
        n = bag_io.recover_bag(tmp_path / "dead", tmp_path / "back")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert n == 750
    assert peak < size / 4, f"recover's peak {peak / 1e6:.1f} MB for a {size / 1e6:.1f} MB recording"
    back = read_raw_messages(tmp_path / "back", ["output"])
    assert [(m.log_time, m.data) for m in back] == sent


def _split_copy(raw, path, flush_every=10, **limits):
    """The messages ``raw`` written again by a BagWriter with split storage, flushed every ``flush_every``
    messages; returns the open writer (close it)."""
    w = BagWriter(path, fsync=False, **limits)
    for k, m in enumerate(raw):
        if not w.has_topic(m.topic):
            w.add_topic(m.topic, m.msgtype, [bag_io.contract_vector_qos()])
        w.write(m.topic, m.log_time, m.data)
        if k % flush_every == flush_every - 1:
            w.flush()
    return w


@pytest.mark.parametrize("limits", [{"split_bytes": 8000}, {"split_seconds": 4.0}], ids=["bytes", "seconds"])
def test_a_split_bag_reads_as_the_same_bag_in_one_file(tmp_path, limits):
    """Split storage (``ros2 bag record --max-bag-size`` / ``--max-bag-duration``): storage files
    NAME_0.mcap, NAME_1.mcap, ... each closed at the first flush past the limit, a metadata.yaml that lists
    them with their counts and times, and the same samples, messages and order as the bag in one file."""
    r, u, y = _samples(40)
    src = write_bag(tmp_path / "src", r, u, y)
    raw = read_raw_messages(src, ["setpoint", "input", "output"])
    w = _split_copy(raw, tmp_path / "split", **limits)
    w.close()
    bag = tmp_path / "split"
    files = sorted(f.name for f in bag.iterdir())
    n_files = len(files) - 1
    assert n_files >= 3 and files == sorted(["metadata.yaml"] + [f"split_{k}.mcap" for k in range(n_files)])
    assert w.storage_files == w.closed_files == [f"split_{k}.mcap" for k in range(n_files)]
    import yaml

    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["relative_file_paths"] == [f"split_{k}.mcap" for k in range(n_files)]
    assert [f["path"] for f in meta["files"]] == meta["relative_file_paths"]
    assert meta["message_count"] == sum(f["message_count"] for f in meta["files"]) == len(raw) == 120
    assert {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]} == \
        {"/setpoint": 40, "/input": 40, "/output": 40}
    # Each file but the last closed at the first flush past the limit (a flush every 10 messages: 3 1/3 samples
    # of 0.5 s, under 1,500 bytes of records); the size is that of the file at that flush, before what closing it
    # adds (the metadata record, opcode 0x0C, and the summary).
    for entry in meta["files"][:-1]:
        if "split_seconds" in limits:
            assert 4e9 <= entry["duration"]["nanoseconds"] < 4e9 + 2e9
        else:
            data = (bag / entry["path"]).read_bytes()
            size = next(start for op, start, _ in _records_of(data) if op == 0x0C) - 9
            assert 8000 <= size < 8000 + 1500
    first, last = min(m.log_time for m in raw), max(m.log_time for m in raw)
    assert meta["starting_time"]["nanoseconds_since_epoch"] == first
    assert meta["duration"]["nanoseconds"] == last - first
    back = read_raw_messages(bag, ["setpoint", "input", "output"])
    assert [(m.topic, m.log_time, m.data) for m in back] == [(m.topic, m.log_time, m.data) for m in raw]
    one = read_bag(src, MODEL)
    split = read_bag(bag, MODEL)
    for name in ("t", "r", "u", "y"):
        np.testing.assert_array_equal(getattr(split, name), getattr(one, name))
    from mpm_monitor.io.bags.mcap_records import CHUNK, CHUNK_CRC_OFFSET, MAGIC

    for mcap in files[1:]:              # each storage file is closed on its own, with its chunks' CRCs
        data = (bag / mcap).read_bytes()
        crcs = [struct.unpack_from("<I", body, CHUNK_CRC_OFFSET)[0]
                for op, _, body in _records_of(data) if op == CHUNK]
        assert data.endswith(MAGIC) and crcs and all(crcs)


def test_a_split_recording_killed_is_recovered_from_every_storage_file(tmp_path):
    """A recorder with split storage killed: closed storage files, the one being written (no summary), and the
    empty directory it was created in.  ``recover`` gets back every flushed message, in order."""
    import shutil

    r, u, y = _samples(40)
    raw = read_raw_messages(write_bag(tmp_path / "src", r, u, y), ["setpoint", "input", "output"])
    w = _split_copy(raw[:100], tmp_path / "live", split_bytes=3000)
    for m in raw[100:]:
        w.write(m.topic, m.log_time, m.data)        # not flushed: lost with the process
    shutil.copytree(tmp_path / "live", tmp_path / "dead")   # what a kill leaves on disk
    w.close()
    left = sorted(f.name for f in (tmp_path / "dead").iterdir())
    k = len(w.closed_files) - 1                     # the file being written at the kill
    assert f".split_{k}" in left and f"live_{k}.mcap" in left and "metadata.yaml" not in left and k >= 2
    notes = []
    assert bag_io.recover_bag(tmp_path / "dead", tmp_path / "back", warn=notes.append) == 100
    back = read_raw_messages(tmp_path / "back", ["setpoint", "input", "output"])
    assert [(m.topic, m.log_time, m.data) for m in back] == [(m.topic, m.log_time, m.data) for m in raw[:100]]
    assert notes == []


def test_split_storage_frees_each_files_chunk_index(tmp_path):
    """An MCAP writer keeps an index entry per chunk (per flush) until its file closes: about 210 bytes a
    flush, 18 MB a day at one flush a second, for as long as a recorder runs.  With split storage each file
    closes and frees its index, so the memory stops growing."""
    import gc
    import tracemalloc

    from mpm_monitor.io.bags.write import joint_state_cdr

    msg = joint_state_cdr(TS, 0, ["x1", "x2"], np.zeros(2))
    growth = {}
    for label, limits in (("one file", {}), ("split", {"split_bytes": 20_000})):
        w = BagWriter(tmp_path / label.replace(" ", "_"), fsync=False, **limits)
        w.add_topic("/output", JS.__msgtype__)
        tracemalloc.start()
        try:
            points, files = [], 0
            for k in range(3000):
                w.write("/output", k * 10**9, msg)
                w.flush()
                # Measured where a file has just closed (split: the index of the file being written grows
                # between two splits), from the 500th flush on.
                if k >= 499 and (len(w.closed_files) != files if limits else k in (499, 2999)):
                    gc.collect()        # closing a file leaves cycles (YAML loaders) to the collector
                    points.append((k, tracemalloc.get_traced_memory()[0]))
                files = len(w.closed_files)
            (k0, m0), (k1, m1) = points[0], points[-1]
            assert k1 - k0 > 2000, points
            growth[label] = (m1 - m0) / (k1 - k0)
        finally:
            tracemalloc.stop()
        w.close()
    assert growth["one file"] > 150, growth          # bytes a flush
    assert growth["split"] < 20, growth


def test_a_negative_split_limit_is_refused(tmp_path):
    with pytest.raises(BagError, match=r"split limits must be 0 \(none\) or positive"):
        BagWriter(tmp_path / "bag", split_bytes=-1)
    assert not (tmp_path / "bag").exists()


def test_recover_of_a_file_killed_before_its_magic_reached_the_disk_has_no_message(tmp_path):
    """A recorder killed before its first write leaves an empty (or partial-magic) storage file: "no complete
    message to recover", as the docs say, not "not an MCAP file (bad magic)"."""
    from mpm_monitor.io.bags.mcap_records import MAGIC

    for name, content in (("empty", b""), ("part", MAGIC[:3])):
        (tmp_path / name).mkdir()
        (tmp_path / name / f"{name}.mcap").write_bytes(content)
        with pytest.raises(BagError) as e:
            bag_io.recover_bag(tmp_path / name, tmp_path / f"{name}_back")
        _check(e, f"{name}.mcap: no complete message to recover (expected at least one complete chunk")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "junk.mcap").write_bytes(b"garbage!!")
    with pytest.raises(BagError, match="not an MCAP file"):
        bag_io.recover_bag(tmp_path / "junk", tmp_path / "junk_back")


def test_bad_values_as_gaps_in_a_bag(tmp_path):
    """A message holding NaN is refused by default; with bad_values='gap' it is left out, its sample a gap, and
    the data are those of the bag without it, with a note per topic.  A topic of NaN only is named."""
    r, u, y = _samples(30)
    y[7, 1] = np.nan
    u[12, 0] = np.inf
    bag = write_bag(tmp_path / "bag", r, u, y)
    with pytest.raises(BagError, match=r"topic '/output': message 8 \(stamp .* s\) holds a non-finite value"):
        read_bag(bag, MODEL)
    data = read_bag(bag, MODEL, bad_values="gap")
    keep = np.setdiff1d(np.arange(30), [7, 12])
    ref = read_bag(write_bag(tmp_path / "ref", r[keep], u[keep], y[keep],
                             stamps=np.rint((T0 + 0.5 * keep) * 1e9).astype(np.int64)), MODEL)
    for key in ("t", "r", "u", "y"):
        np.testing.assert_array_equal(getattr(data, key), getattr(ref, key))
    assert data.n_samples == 28 and len(data.segments) == 3
    assert [n.split(": ", 1)[1] for n in data.notes] == [
        f"topic '/output': 1 message holding a non-finite value left out (the first stamped {T0 + 3.5:g} s); the "
        f"analysis goes around its sample as gaps",
        f"topic '/input': 1 message holding a non-finite value left out (the first stamped {T0 + 6:g} s); the "
        f"analysis goes around its sample as gaps"]
    # A sample whose other message is finite is no gap: the note said the analysis went around it.
    r2, u2, y2 = _samples(30)
    again = read_bag(write_bag(tmp_path / "again", r2, u2, y2, again={("output", 9): np.nan}), MODEL,
                     bad_values="gap")
    np.testing.assert_array_equal(again.y, y2)
    assert [n.split(": ", 1)[1] for n in again.notes] == [
        f"topic '/output': 1 message holding a non-finite value left out (the first stamped {T0 + 4.5:g} s); it was "
        f"sent again with finite values for its sample, which is kept"]
    y[:] = np.nan
    with pytest.raises(BagError, match=r"topic '/output': every one of its 30 messages holds a non-finite value"):
        read_bag(write_bag(tmp_path / "nan", r, u, y), MODEL, bad_values="gap")


def test_export_bad_values_gap_leaves_the_sample_out_of_the_csv(tmp_path, capsys):
    """``export --bad-values gap``: a message holding NaN leaves its sample out of the CSV (t skips it), with the
    note as a warning, with a model or without; by default the export is refused as before."""
    r, u, y = _samples(20)
    y[5, 0] = np.nan
    bag = write_bag(tmp_path / "bag", r, u, y)
    assert cli_main(["export", "--bag", str(bag), "--csv", str(tmp_path / "a.csv")]) == 2
    assert "holds a non-finite value" in capsys.readouterr().err
    save_model(MODEL, tmp_path / "m.yaml")
    for args in ([], ["--model", str(tmp_path / "m.yaml")]):
        out = tmp_path / f"b{len(args)}.csv"
        assert cli_main(["export", "--bag", str(bag), "--csv", str(out), "--bad-values", "gap"] + args) == 0
        err = capsys.readouterr().err
        assert "topic '/output': 1 message holding a non-finite value left out" in err
        data = read_csv(out, MODEL)
        np.testing.assert_allclose(data.t, T0 + 0.5 * np.delete(np.arange(20), 5))
        np.testing.assert_array_equal(data.y, np.delete(y, 5, axis=0))


def test_an_output_logged_at_half_rate_is_refused_without_a_model_with_the_reason(tmp_path):
    """Without a model the output topic's spacing is the sample time: a recorder that kept every other output
    message makes the other topics' stamps fall between its samples.  They were refused as "off the sample
    grid"; the refusal now names both spacings and --model, with which the bag is read (the output's missing
    samples as gaps)."""
    r, u, y = _samples(40)
    bag = write_bag(tmp_path / "bag", r, u, y, skip={("output", k) for k in range(1, 40, 2)})
    with pytest.raises(BagError) as exc:
        read_bag_channels(bag)
    _check(exc, "topic '/setpoint' sends every 0.5 s", "output topic '/output' every 1 s", "--model")
    assert len(str(exc.value).splitlines()) == 1
    data = read_bag(bag, MODEL, bad_values="gap")
    assert data.sample_time == 0.5 and data.n_samples == 20
    np.testing.assert_array_equal(data.u, u[::2])
    assert read_bag_channels(write_bag(tmp_path / "full", r, u, y)).sample_time == 0.5
