"""The live view's picture in the logs (issue 30): a kept flight's MCAP carries the scene,
transforms and annotations the live view serves, and ``visland log frame`` draws a moment of it
as a PNG."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import visland
from mcap.reader import make_reader

from companion.flightlog import FlightLogError, read_log
from companion.live.messages import protobuf_decoder
from companion.live.scene_log import SCENE_TOPICS, add_scene

pytest.importorskip("foxglove")


def _messages(path, topics):
    """topic -> [(log_time, decoded message)] (protobuf by its schema record, JSON as JSON)."""
    out: dict[str, list] = {t: [] for t in topics}
    with open(path, "rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages(topics=list(topics)):
            if channel.message_encoding == "json":
                value = json.loads(msg.data)
            else:
                value = protobuf_decoder(schema.name, schema.data)(msg.data)
            out[channel.topic].append((msg.log_time, value))
    return out


@pytest.fixture(scope="module")
def kept(tmp_path_factory):
    """One flight of the shipped model kept by ``visland eval --keep-logs --keep all``."""
    out = tmp_path_factory.mktemp("kept")
    r = visland(
        "eval", "--policy", "models/visland_vision.pt", "--episodes", "1",
        "--keep-logs", str(out), "--keep", "all", "--json",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    (row,) = json.loads(r.stdout)["per_episode"]
    assert row["success"], row
    return row["log"]


def test_card_eval_keep_logs_carries_the_live_views_scene(kept):
    topics = ("/camera/image", *SCENE_TOPICS[:-1])
    got = _messages(kept, topics)
    frames = len(got["/camera/image"])
    assert frames > 100
    for topic in topics:
        assert len(got[topic]) == frames, topic  # one of each per camera frame
    # each frame's annotations carry its image's own stamp, at its log time
    images = {t: m["timestamp"] for t, m in got["/camera/image"]}
    for t, ann in got["/camera/annotations"]:
        assert (ann.points[0].timestamp.seconds, ann.points[0].timestamp.nanos) == (
            images[t]["sec"],
            images[t]["nsec"],
        )
    assert all(a.texts for _, a in got["/camera/annotations"][frames // 2 :])  # the CNN's bearing
    late = got["/scene"][-1][1]
    assert {"pad", "vehicle", "frustum", "trajectory"} <= {e.id for e in late.entities}
    state = got["/live/state"][-1][1]
    assert {"truth", "estimate", "command"} <= set(state)
    assert abs(state["truth"]["d"]) < 1.0  # on the ground at the end
    frames_tf = {t.child_frame_id for t in got["/tf"][0][1].transforms}
    assert {"vehicle", "camera"} <= frames_tf
    # the log's own records are untouched: it reads as before, complete, with its result
    log = read_log(kept)
    assert not log.truncated and log.topic("/episode/result")[-1]["success"]
    info = visland("log", "info", kept, "--json")
    assert json.loads(info.stdout)["topics"]["/scene"]["count"] == frames


def test_log_scene_again_changes_nothing_and_a_cut_log_gets_its_readable_part(kept, tmp_path):
    again = tmp_path / "again.mcap"
    report = add_scene(kept, again)
    counts = {t: len(v) for t, v in _messages(kept, SCENE_TOPICS).items()}
    assert {t: len(v) for t, v in _messages(again, SCENE_TOPICS).items()} == counts
    assert report.frames == counts["/scene"] and not report.truncated
    cut = tmp_path / "cut.mcap"
    data = again.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    r = visland("log", "scene", str(cut), "--json")
    assert r.returncode == 0, r.stderr
    (done,) = json.loads(r.stdout)
    assert done["truncated"] and 0 < done["frames"] < report.frames
    assert not read_log(cut).truncated  # rewritten whole


def test_log_scene_names_what_it_cannot_draw(tmp_path):
    bad = tmp_path / "notes.mcap"
    bad.write_text("not a log")
    r = visland("log", "scene", str(bad))
    assert r.returncode == 2 and "notes.mcap" in r.stderr and "not an MCAP" in r.stderr
    from companion.flightlog import FlightLogWriter

    empty = tmp_path / "no_camera.mcap"
    with FlightLogWriter(empty, reproducible=True) as w:
        w.write("/events", "visland.Event", 0.0, {"kind": "flight", "text": "start"})
    with pytest.raises(FlightLogError, match="no /camera/image"):
        add_scene(empty)
    assert empty.read_bytes()[:8] == b"\x89MCAP0\r\n"  # left as it was


def test_card_log_frame_draws_the_camera_with_its_annotations_and_the_scene(kept, tmp_path):
    import matplotlib.image

    out = tmp_path / "frame.png"
    r = visland("log", "frame", kept, "--time", "5", "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert abs(report["time_s"] - 5.0) < 0.11 and report["pad_probability"] > 0.5
    assert report["estimate_error_m"] < 2.0 and 40 < report["altitude_m"] < 100
    png = matplotlib.image.imread(out)
    assert png.shape[0] >= 500 and png.shape[1] >= 1000
    camera = png[:, : png.shape[1] // 2, :3]
    # the camera is grey; the annotations are the only coloured pixels on its half
    colour = np.ptp(camera, axis=2) > 0.3
    assert colour.sum() > 50
    # by default: where the estimate was worst
    r = visland("log", "frame", kept, "--json")
    assert r.returncode == 0 and "furthest" in json.loads(r.stdout)["why"]
