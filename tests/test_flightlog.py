"""MCAP flight logs: round trip, Foxglove schemas, truncated and corrupt files, crash bound."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from companion.contract.topics import TOPIC_GROUNDTRUTH, TOPIC_IMAGE
from companion.flightlog import FlightLogError, FlightLogWriter, read_log


def _write(path, n=40):
    with FlightLogWriter(path, {"config": {"seed": 3, "planet": "earth"}}) as w:
        for k in range(n):
            t = k * 0.1
            w.write_image(t, np.full((128, 128), k % 256, np.uint8), k)
            w.write(TOPIC_GROUNDTRUTH, "visland.GroundTruth", t, {"pos_ned_m": [k, 0.0, -1.0]})
            w.write_pose(t, [k, 0.0, -1.0], [1.0, 0.0, 0.0, 0.0])


def test_round_trip(tmp_path):
    path = tmp_path / "f.mcap"
    _write(path)
    log = read_log(path)
    assert not log.truncated and log.error is None
    assert log.metadata["config"] == {"seed": 3, "planet": "earth"}
    times, frames = log.images()
    assert frames.shape == (40, 128, 128) and frames[7, 5, 5] == 7
    np.testing.assert_allclose(times, np.arange(40) * 0.1)
    assert [m["pos_ned_m"][0] for m in log.topic(TOPIC_GROUNDTRUTH)] == list(range(40))
    assert log.duration_s == pytest.approx(3.9)


def test_schemas_are_foxglove_names_with_json_schema(tmp_path):
    from mcap.reader import make_reader

    path = tmp_path / "f.mcap"
    _write(path, 3)
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    schemas = {s.name: json.loads(s.data) for s in summary.schemas.values()}
    assert {"foxglove.RawImage", "foxglove.PoseInFrame", "visland.GroundTruth"} <= set(schemas)
    assert all(s["type"] == "object" and s["title"] == n for n, s in schemas.items())
    assert all(c.message_encoding == "json" for c in summary.channels.values())


def test_truncated_file_gives_its_prefix(tmp_path):
    path = tmp_path / "f.mcap"
    _write(path, 60)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    log = read_log(cut)
    assert log.truncated and log.error
    n = len(log.topic(TOPIC_IMAGE))
    assert 0 < n < 60
    assert [m["time_s"] for m in log.topic(TOPIC_IMAGE)] == pytest.approx(np.arange(n) * 0.1)


@pytest.mark.parametrize(
    "content", [b"", b"not an mcap file at all", b"\x89MCAP0\r\n" + b"\xff" * 64]
)
def test_corrupt_files(tmp_path, content):
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    if content.startswith(b"\x89MCAP0\r\n"):
        log = read_log(path)  # right magic, garbage after: an empty, truncated log
        assert log.truncated and not log.messages
    else:
        with pytest.raises(FlightLogError, match=r"bad\.mcap: not an MCAP file"):
            read_log(path)
    with pytest.raises(FlightLogError, match="cannot open"):
        read_log(tmp_path / "missing.mcap")


def test_sigkill_loses_at_most_the_last_second(tmp_path):
    """A process killed mid-flight loses at most the last second of what it wrote.

    Measured on the writer's own clock — the sim time of the last record it wrote (it reports
    each on stdout after writing it) vs the last record readable from the file — so a slow
    scheduler that delays the writer cannot move the figure: the writer flushes at the first
    write 1 s (sim or wall) after its last flush, whenever that write comes.
    """
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(
        f"""
        import time
        import numpy as np
        from companion.contract.topics import TOPIC_GROUNDTRUTH
        from companion.flightlog import FlightLogWriter
        w = FlightLogWriter({str(path)!r})
        k = 0
        while True:  # real time: 10 Hz frames and state, until killed
            t = k / 10
            w.write_image(t, np.zeros((128, 128), np.uint8), k)
            w.write(TOPIC_GROUNDTRUTH, "visland.GroundTruth", t, {{"k": k}})
            print(k, flush=True)
            k += 1
            time.sleep(0.1)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "0"  # the first record is written
        time.sleep(3.5)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        written = [int(line) for line in proc.stdout.read().split()]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    log = read_log(path)
    last = log.topic(TOPIC_GROUNDTRUTH)[-1]["k"]
    assert written, "the writer reported no record after the first"
    # records are 0.1 s of sim time apart: at most 9 written after the last flushed one
    assert written[-1] - last <= 9, (written[-1], last)


def _random_value(rng: np.random.Generator, depth: int = 0):
    """A message-like value mixing every type a log message may hold."""
    specials = [float("nan"), float("inf"), -float("inf"), 1e308, -0.0]
    kind = int(rng.integers(0, 14 if depth < 3 else 7))
    if kind == 0:
        return float(rng.normal())
    if kind == 1:
        return specials[int(rng.integers(0, len(specials)))]
    if kind == 2:
        return int(rng.integers(-5, 5))
    if kind == 3:
        return [True, False, None, "text"][int(rng.integers(0, 4))]
    if kind == 4:
        return np.float64(rng.normal()) if rng.random() < 0.5 else np.float32("nan")
    if kind == 5:
        return np.int32(7) if rng.random() < 0.5 else np.bool_(True)
    if kind == 6:
        return np.uint8(200)
    if kind == 7:
        arr = rng.normal(size=int(rng.integers(0, 5)))
        if arr.size and rng.random() < 0.3:
            arr[int(rng.integers(0, arr.size))] = specials[int(rng.integers(0, 3))]
        return arr.astype([np.float64, np.float32][int(rng.integers(0, 2))])
    if kind == 8:
        return rng.integers(0, 9, size=(2, 3)).astype(np.float64)  # 2-D
    if kind == 9:
        return np.array([1e308, 1e308])  # finite, but the sum overflows
    if kind == 10:
        return rng.integers(-3, 3, size=3).astype([np.int64, np.uint16, np.bool_][depth % 3])
    if kind == 11:
        return tuple(_random_value(rng, depth + 1) for _ in range(int(rng.integers(0, 4))))
    if kind == 12:
        return [_random_value(rng, depth + 1) for _ in range(int(rng.integers(0, 4)))]
    keys = ["a", 3, 2.5, "b"]
    return {keys[i % 4]: _random_value(rng, depth + 1) for i in range(int(rng.integers(0, 5)))}


def test_fast_json_conversion_is_exactly_the_reference_one():
    from types import MappingProxyType

    from companion.flightlog import _jsonable, _jsonable_slow

    rng = np.random.default_rng(5)
    for _ in range(3000):
        value = {"v": _random_value(rng), "proxy": MappingProxyType({1: np.zeros(2)})}
        fast, slow = _jsonable(value), _jsonable_slow(value)
        assert json.dumps(fast) == json.dumps(slow)
        assert json.dumps(fast, allow_nan=False)  # no NaN/inf ever reaches the JSON text


def test_message_text_is_the_converted_messages_json_exactly():
    """A message goes out as its JSON where nothing needs converting, else through
    :func:`_jsonable`: the text is the converted message's either way."""
    from companion.flightlog import _COMPACT_JSON, _encode, _jsonable

    rng = np.random.default_rng(7)
    for k in range(3000):
        msg = {"v": _random_value(rng), "w": _random_value(rng), "n": k}
        reference = _COMPACT_JSON.encode({"time_s": k * 0.004, **_jsonable(msg)}).encode()
        assert _encode(k * 0.004, msg) == reference


def _write_all(path, lean: bool, messages) -> bytes:
    writer = FlightLogWriter(path, {"config": {"a": 1}}, reproducible=True)
    assert writer._append is not None  # mcap 1.6.0 is laid out as mcap_chunks expects
    assert "_Writer__finalize_chunk" in vars(writer._writer)
    if not lean:  # mcap's own add_message and chunk finalisation
        writer._append = None
        del writer._writer._Writer__finalize_chunk
    for topic, t, body in messages:
        writer.write(topic, "test.Body", t, body)
    writer.close()
    return path.read_bytes()


def test_lean_message_append_and_chunks_write_mcaps_bytes(tmp_path, monkeypatch):
    """The writer's own Message records (statistics, chunk index, chunk size) and chunks
    (compressed at level 1) give the file mcap's Writer gives at that level, byte for byte,
    across many chunks and channels."""
    import zstandard
    from mcap import writer as mcap_writer

    level_1 = zstandard.ZstdCompressor(level=1)
    monkeypatch.setattr(mcap_writer.zstandard, "compress", level_1.compress)
    rng = np.random.default_rng(3)
    messages = [
        (f"/t{int(rng.integers(0, 5))}", 0.004 * k, {"x": float(rng.normal()), "pad": "p" * 900})
        for k in range(2000)
    ]
    lean = _write_all(tmp_path / "lean.mcap", True, messages)
    assert lean == _write_all(tmp_path / "mcap.mcap", False, messages)
    log = read_log(tmp_path / "lean.mcap")
    assert sum(len(v) for v in log.messages.values()) == 2000 and not log.truncated


def test_image_records_spliced_are_the_records_json(tmp_path):
    """A frame's base64 text spliced into its record's JSON gives the bytes of the whole
    record through the JSON encoder, and reads back as the image."""
    from companion.contract.records import RawImageRecord

    image = np.random.default_rng(1).integers(0, 256, (24, 32)).astype(np.uint8)
    paths = []
    for splice in (True, False):
        path = tmp_path / f"{splice}.mcap"
        writer = FlightLogWriter(path, reproducible=True)
        for k in range(3):
            record = RawImageRecord.mono8(image, k, 1000 + k, frame_number=k, rx_s=0.5 * k)
            if splice:
                writer.write_image_record(TOPIC_IMAGE, 0.1 * k, record)
            else:
                writer.write_record(TOPIC_IMAGE, 0.1 * k, record)
        writer.close()
        paths.append(path)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    _, frames = read_log(paths[0]).images()
    assert frames.shape == (3, 24, 32) and (frames == image).all()


def test_mavlink_fields_are_pymavlinks_to_dict():
    from pymavlink.dialects.v20 import common as mavlink

    from companion.flightlog import mavlink_fields

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    covariance = [float("nan")] + [0.0] * 20
    odometry = (5, 1, 12, 1.0, 2.0, 3.0, [1.0, 0, 0, 0], 0, 0, 0, 0, 0, 0, covariance)
    messages = [
        mav.attitude_encode(12, 0.1, -0.2, np.float64(0.3), 0.0, float("nan"), 3),
        mav.odometry_encode(*odometry, [0.0] * 21, 0, 0, 100),
        mav.statustext_encode(6, b"mode OFFBOARD"),
        mav.param_value_encode(b"MPC_THR_HOVER", 0.4, 9, 10, 3),
        mav.setup_signing_encode(1, 1, [7] * 32, 0),
    ]
    mav2 = mavlink.MAVLink(None)  # and as received: decoded from the wire
    received = [mav2.parse_buffer(m.pack(mav))[0] for m in messages]
    for msg in messages + received:
        assert mavlink_fields(msg) == msg.to_dict()
        assert list(mavlink_fields(msg)) == list(msg.to_dict())
