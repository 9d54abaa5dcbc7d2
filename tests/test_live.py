"""The live view (issue 30): a Foxglove WebSocket server in the flying process; a client of the
Foxglove protocol subscribes and decodes what it serves."""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import numpy as np
import pytest

from companion.live import LiveFrame, LiveView, parse_live
from tools.live_client import watch
from training.exec.fly import DEFAULT_VISION_POLICY, FlyConfig, fly

TOPICS = {
    "/camera/image",
    "/camera/calibration",
    "/camera/annotations",
    "/scene",
    "/tf",
    "/live/state",
}


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _vision_live(tmp_path, port: int, **fields) -> FlyConfig:
    """One lockstep flight of the shipped vision model with the companion's live view on
    ``port`` (``fields``: e.g. the companion mode)."""
    return FlyConfig(
        policy=DEFAULT_VISION_POLICY,
        episodes=1,
        out=str(tmp_path / "run"),
        progress=False,
        live=str(port),
        companion_args=("--max-age-ms", "3000"),
        sitl_args=("--lockstep-timeout-s", "5"),
        **fields,
    )


def _watched_flight(cfg: FlyConfig, port: int, per_topic: int):
    """``fly(cfg)`` on a thread while a Foxglove-protocol client watches ``port``: the report
    and what the client saw."""
    result: dict = {}
    flight = threading.Thread(target=lambda: result.update(report=fly(cfg)))
    flight.start()
    try:
        seen = watch(port, TOPICS, per_topic=per_topic, timeout_s=60.0)
    finally:
        flight.join(180)
    return result["report"], seen


def test_parse_live_takes_host_and_port_and_names_a_bad_one():
    assert parse_live("8765") == ("127.0.0.1", 8765)
    assert parse_live("0.0.0.0:9000") == ("0.0.0.0", 9000)
    for bad in ("", "host:", "99999", "port"):
        with pytest.raises(ValueError, match=r"\[HOST:\]PORT"):
            parse_live(bad)


def test_nothing_is_built_without_a_client_and_everything_with_one():
    view = LiveView(port=0)
    try:
        assert not view.watched
        frame = LiveFrame(
            time_s=1.5,
            image=np.full((128, 128), 77, np.uint8),
            vehicle_pos_ned_m=np.array([2.0, -1.0, -30.0]),
            quat_wxyz=np.array([1.0, 0.0, 0.0, 0.0]),
            perception=(0.05, -0.02, 0.97),
            estimate_rel_ned_m=np.array([2.3, -1.2, -30.0]),
            estimate_sigma_m=np.array([0.4, 0.4, 0.3]),
            truth_rel_ned_m=np.array([2.0, -1.0, -30.0]),
            command=(0.55, 0.01, -0.02, 0.0),
            range_m=30.1,
            wind_ned_m_s=np.array([4.0, 1.0, 0.0]),
            state="flying",
        )
        view.publish(frame)  # nobody watches: builds nothing, costs nothing
        stop = threading.Event()

        def pump() -> None:
            while not stop.wait(0.05):
                view.publish(frame)

        threading.Thread(target=pump, daemon=True).start()
        try:
            seen = watch(view.port, TOPICS)
        finally:
            stop.set()
    finally:
        view.close()
    assert seen.channels["/camera/image"]["schemaName"] == "foxglove.RawImage"
    image = seen.messages["/camera/image"][0]
    assert (image.width, image.height, image.encoding) == (128, 128, "mono8")
    assert set(image.data) == {77}
    notes = seen.messages["/camera/annotations"][0]
    assert notes.texts[0].text == "pad p=0.97" and len(notes.circles) == 1
    # the CNN's cross at its bearing: 64 + f tan(right), 64 - f tan(forward)
    f = 64 / np.tan(np.radians(22.5))
    centre = np.mean([(p.x, p.y) for p in notes.points[0].points], axis=0)
    assert centre == pytest.approx([64 + f * 0.05, 64 + f * 0.02], abs=1e-3)
    scene = seen.messages["/scene"][0]
    ids = {e.id for e in scene.entities}
    assert {"ground", "pad", "vehicle", "frustum", "estimated_pad", "wind"} <= ids
    tf = {t.child_frame_id: t for t in seen.messages["/tf"][0].transforms}
    assert tf["vehicle"].translation.z == pytest.approx(-30.0)
    state = seen.messages["/live/state"][0]
    assert state["command"]["thrust_norm"] == pytest.approx(0.55)
    assert state["estimate"]["n"] == pytest.approx(2.3) and state["truth"]["n"] == 2.0


def test_card_fly_live_serves_the_companions_view_of_a_vision_flight(tmp_path):
    """``visland fly --live PORT``: the companion serves its camera, the CNN's bearing and its
    estimate over the truth; the flight lands as it does without a viewer."""
    port = _free_tcp_port()
    report, seen = _watched_flight(_vision_live(tmp_path, port), port, per_topic=3)
    assert report.summary.success_rate == 1.0, report.per_episode
    image = seen.messages["/camera/image"][-1]
    assert (image.width, image.height) == (128, 128) and len(set(image.data)) > 10
    assert any(n.texts for n in seen.messages["/camera/annotations"])  # the CNN's bearing
    ids = {e.id for m in seen.messages["/scene"] for e in m.entities}
    assert {"pad", "vehicle", "frustum"} <= ids
    states = seen.messages["/live/state"]
    assert all("truth" in s and "command" in s for s in states)  # the SITL's truth beside it
    # the recorded flights, replayed live: the companion's own log names its policy (run again
    # for the CNN and the estimate); the SITL's log has the truth
    from tools.log_replay import ReplayConfig, replay_live

    (companion_log,) = (tmp_path / "run" / "companion").glob("*.mcap")
    (sitl_log,) = (tmp_path / "run" / "sitl").glob("*.mcap")
    for log, key in ((companion_log, "estimate"), (sitl_log, "truth")):
        port = _free_tcp_port()
        out: dict = {}
        cfg = ReplayConfig(file=log, live=str(port), speed=0.0, wait_s=30.0)
        player = threading.Thread(target=lambda cfg=cfg, out=out: out.update(r=replay_live(cfg)))
        player.start()
        try:
            seen = watch(port, TOPICS, per_topic=50, timeout_s=60.0)
        finally:
            player.join(60)
        assert out["r"].watched and out["r"].frames > 100
        late = seen.messages["/live/state"][-1]
        assert key in late and "command" in late, late
        if key == "estimate":
            assert out["r"].policy == DEFAULT_VISION_POLICY or out["r"].policy.endswith(".pt")
            assert any(n.texts for n in seen.messages["/camera/annotations"])
    # the companion's log with the live view's picture written into it (visland log scene):
    # its policy run again for the CNN and the estimate, its events as foxglove.Log on /log
    from companion.live.scene_log import add_scene

    scene = add_scene(companion_log)
    assert scene.policy and scene.frames > 100 and scene.events > 3, scene


def test_log_replay_of_a_missing_file_exits_2_naming_it(tmp_path):
    from helpers import visland

    port = str(_free_tcp_port())
    proc = visland("log", "replay", str(tmp_path / "nope.mcap"), "--live", port, "--wait-s", "0")
    assert proc.returncode == 2 and "nope.mcap" in proc.stderr
    proc = visland("log", "replay", str(tmp_path / "x.mcap"), "--live", "host:port")
    assert proc.returncode == 2 and "[HOST:]PORT" in proc.stderr


def test_the_shipped_layout_shows_only_topics_the_live_view_serves():
    import json
    from pathlib import Path

    layout = json.loads(Path("docs/foxglove/visland.json").read_text())
    panels = layout["configById"]
    served = TOPICS | {"/log"}
    named = set()
    for config in panels.values():
        text = json.dumps(config)
        named |= {t for t in served if f'"{t}' in text}
        for path in config.get("paths", []):
            topic = path["value"].split(".")[0]
            assert topic in served, path
    assert {"/camera/image", "/camera/annotations", "/scene", "/live/state", "/log"} <= named
    text = json.dumps(layout["layout"])
    assert all(panel in text for panel in panels)  # every panel is placed


def test_card_sitl_live_serves_the_truth_with_the_pad_on_its_rover(tmp_path):
    """``visland sitl --live PORT``: the SITL's view — the true vehicle, the pad where its rover
    has driven it, the command flown — while the expert lands on the rover's roof."""
    port = _free_tcp_port()
    cfg = FlyConfig(
        policy="expert",
        scenario="configs/sites/rover_fast.toml",
        episodes=1,
        seed=500,
        render=True,
        out=str(tmp_path / "run"),
        progress=False,
        sitl_args=("--live", str(port), "--lockstep-timeout-s", "5"),
        companion_args=("--max-age-ms", "3000"),
    )
    report, seen = _watched_flight(cfg, port, per_topic=60)
    assert report.summary.success_rate == 1.0
    pads = [
        t.translation
        for m in seen.messages["/tf"]
        for t in m.transforms
        if t.child_frame_id == "pad"
    ]
    assert abs(pads[-1].x - pads[0].x) + abs(pads[-1].y - pads[0].y) > 1.0  # the rover drove
    states = seen.messages["/live/state"]
    assert any("command" in s for s in states) and all("truth" in s for s in states)
    assert seen.messages["/camera/image"][-1].width == 128


def test_card_landing_target_mode_serves_its_camera_and_estimate_live(tmp_path):
    """``fly --companion-mode landing-target --live``: the companion's CNN bearing and
    estimate go to the viewer while the autopilot lands."""
    port = _free_tcp_port()
    cfg = _vision_live(tmp_path, port, companion_mode="landing-target")
    report, seen = _watched_flight(cfg, port, per_topic=20)
    assert report.summary.success_rate == 1.0, report.per_episode
    assert any(n.texts for n in seen.messages["/camera/annotations"])
    assert any("estimate" in s and "truth" in s for s in seen.messages["/live/state"])


def test_log_scene_setting_auto_follows_foxglove_on_needs_it_off_never(monkeypatch, capsys):
    """``log_scene``: 'auto' writes the picture where foxglove-sdk imports and says so on stderr
    where it does not; 'on' without it stops the companion before a link opens, naming the fix;
    'off' never writes it. (foxglove-sdk is installed here: its absence is a module that fails
    to import.)"""
    import sys

    from companion.app import _log_scene
    from companion.config import CompanionConfig, CompanionError

    assert _log_scene("auto") and _log_scene("on") and not _log_scene("off")
    monkeypatch.setitem(sys.modules, "foxglove.messages", None)  # import raises ImportError
    assert not _log_scene("auto")
    assert "visland log scene adds it later" in capsys.readouterr().err
    with pytest.raises(CompanionError, match=r"log_scene = 'on' needs foxglove-sdk"):
        _log_scene("on")
    assert not _log_scene("off")
    with pytest.raises(CompanionError, match="log_scene"):
        CompanionConfig(log_scene="sometimes")


def test_a_taught_pads_log_draws_the_pad_at_its_own_size(tmp_path, capsys):
    """A flight over the 1 m helipad, kept by ``visland eval --keep-logs``: its log carries the
    pad drawn, and the scene built from it (``log replay``/``log frame``, the live view) draws a
    1 m pad, not the paper's 4 m one."""
    from companion.flightlog import read_log
    from companion.live.frame import pad_extent_m
    from companion.live.messages import decoded, scene_update
    from companion.live.replay import REPLAY_TOPICS, logged_frames
    from tools.cli import main

    assert pad_extent_m(None) == (4.0, 4.0)
    assert pad_extent_m({"design": "x", "size_m": [2.0, 1.0]}) == (1.0, 2.0)  # (forward, across)
    scenario = tmp_path / "helipad.toml"
    scenario.write_text(
        Path("configs/scenario.toml").read_text().replace("[75.0, 100.0]", "[18.75, 25.0]")
        + '\n[pad]\ndesign = ["helipad_1m"]\n'
    )
    logs = tmp_path / "logs"
    argv = ["eval", "--policy", "models/visland_vision_helipad_1m.pt", "--scenario", str(scenario)]
    code = main([*argv, "--episodes", "1", "--keep-logs", str(logs), "--keep", "all", "--json"])
    assert code == 0
    (path,) = logs.glob("*.mcap")
    log = read_log(path, REPLAY_TOPICS)
    assert log.metadata["episode"]["pad"]["size_m"] == [1.0, 1.0]
    frames = [f for f in logged_frames(log) if isinstance(f, LiveFrame)]
    assert frames and all(f.pad_size_m == (1.0, 1.0) for f in frames)
    pad = next(e for e in decoded(scene_update(frames[0], [])).entities if e.id == "pad")
    assert (pad.cubes[0].size.x, pad.cubes[0].size.y) == (1.0, 1.0)
