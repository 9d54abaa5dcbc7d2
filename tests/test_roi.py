"""The region of interest at the camera's full resolution (companion/roi.py): the window's
geometry and bearing mapping, the search/track choice, the policy carrying it in its state, an
in-process flight on a 640 x 480 simulator camera, a real-camera source on a video file, and
``visland pad acquire`` end to end."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from companion.camera import CameraError, fit_to_policy
from companion.config import CompanionConfig, CompanionError
from companion.roi import (
    RoiConfig,
    RoiState,
    RoiWindow,
    cut,
    mono8,
    roi_window,
    rotated_geometry,
)
from companion.runtime import PolicyRuntime, level_observation, load_policy_file
from tools.cli import main

W, H, HFOV = 640, 480, 62.2
TAN_HALF = math.tan(math.radians(22.5))


@pytest.fixture(scope="module")
def policy():
    return load_policy_file("models/visland_vision.pt", 1, "torch")


def roi_cfg(**kw) -> RoiConfig:
    return RoiConfig.from_hfov(W, H, HFOV, **kw)


def sim_camera():
    from sitl_sim.config import load_sim

    f = (W / 2) / math.tan(math.radians(HFOV / 2))
    sim = load_sim()
    cam = dataclasses.replace(
        sim.camera, width_px=W, height_px=H, fov_deg=2 * math.degrees(math.atan(H / 2 / f))
    )
    return dataclasses.replace(sim, camera=cam)


# --------------------------------------------------------------------------- geometry


def test_the_view_is_fit_to_policys_crop_bit_for_bit():
    rng = np.random.default_rng(0)
    for cx, cy in ((None, None), (331.0, 229.5)):
        cfg = RoiConfig.from_hfov(W, H, HFOV)
        if cx is not None:
            cfg = dataclasses.replace(cfg, cx_px=cx, cy_px=cy)
        img = rng.integers(0, 256, (H, W), dtype=np.uint8)
        expected = fit_to_policy(img, cfg.fx_px, cx_px=cx, cy_px=cy)
        assert np.array_equal(cut(img, cfg.view()), expected)
    # a BGR frame turned so its top is forward: fit_to_policy's crop, turned the same way
    bgr = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    for turn in (90, 180, 270):
        w, h, cx, cy = rotated_geometry(W, H, 331.0, 229.0, turn)
        turned = mono8(bgr, turn)
        assert turned.shape == (h, w)
        cfg = RoiConfig(w, h, 530.0, cx, cy)
        expected = fit_to_policy(bgr, 530.0, cx_px=331.0, cy_px=229.0, rotate_deg=turn)
        assert np.array_equal(cut(turned, cfg.view()), expected)


def test_a_window_maps_the_cnns_bearing_to_the_cameras_exactly():
    cfg = roi_cfg()
    for window in (
        cfg.view(),
        cfg.tiles()[5],
        cfg.window(412.0, 31.0, 64),
        cfg.window(3, 300, 177),
    ):
        # a point of the full frame, seen in the window's 128 px image at pixel p
        u, v = window.x0 + 0.37 * window.side, window.y0 + 0.81 * window.side
        p = (u - window.x0 + 0.5) * 128 / window.side - 0.5
        q = (v - window.y0 + 0.5) * 128 / window.side - 0.5
        f128 = 64 / TAN_HALF
        raw = np.array([(p - 63.5) / f128, (63.5 - q) / f128, 2.5], dtype=np.float32)
        mapped = window.to_camera(raw)
        assert mapped[0] == pytest.approx((u - cfg.cx_px) / cfg.fx_px, abs=1e-6)
        assert mapped[1] == pytest.approx((cfg.cy_px - v) / cfg.fx_px, abs=1e-6)
        assert mapped[2] == 2.5
        back = window.from_camera(float(mapped[0]), float(mapped[1]))
        assert back == pytest.approx((float(raw[0]), float(raw[1])), abs=1e-6)
    # a 128 px, 45° camera's view is the image itself: the mapping is the identity
    native = RoiConfig(128, 128, 64 / TAN_HALF, 63.5, 63.5)
    assert native.view() == RoiWindow(0, 0, 128, native.fx_px, 63.5, 63.5, "view")
    assert native.view().to_camera(np.array([0.1, -0.2, 1.0])) == pytest.approx([0.1, -0.2, 1.0])


def test_the_track_window_holds_the_pad_at_the_wanted_size_inside_the_frame():
    cfg = roi_cfg(pad_m=1.0, span_px=24.0)
    fx = cfg.fx_px
    w = cfg.track_window(np.array([0.0, 0.0, 20.0]), 0.0)  # 20 m straight down
    assert w.kind == "track" and w.side == round(fx / 20 * 128 / 24)
    assert (w.x0 + (w.side - 1) / 2, w.y0 + (w.side - 1) / 2) == pytest.approx(
        (cfg.cx_px, cfg.cy_px), abs=0.5
    )
    high = cfg.track_window(np.array([0.0, 0.0, 90.0]), 0.0)
    assert high.side == cfg.min_side_px  # no more than 2x upsampling
    low = cfg.track_window(np.array([0.0, 0.0, 3.0]), 0.0)
    assert low.side == cfg.view_side  # never wider than the policy's 45° view
    unsure = cfg.track_window(np.array([0.0, 0.0, 20.0]), 1.0)
    assert unsure.side >= 2 * 3.0 * fx * 1.0 / 20  # the pad within 3 sigma either side
    edge = cfg.track_window(np.array([-30.0, 40.0, 40.0]), 0.0)  # far right and back
    assert edge.x0 + edge.side == W and edge.y0 + edge.side == H
    assert cfg.track_window(np.array([0.0, 0.0, -5.0]), 0.0) is None  # not below the camera


def test_search_then_track_then_search_again():
    cfg = roi_cfg(lost_frames=3)
    tiles = cfg.tiles()
    covered = np.zeros((H, W), bool)
    for t in tiles:
        covered[t.y0 : t.y0 + t.side, t.x0 : t.x0 + t.side] = True
    assert covered.all()
    dist = [math.hypot(t.x0 + 63.5 - cfg.cx_px, t.y0 + 63.5 - cfg.cy_px) for t in tiles]
    assert dist == sorted(dist)  # nearest the image centre first
    st = cfg.start()
    assert st.window == cfg.view()
    rot = np.eye(3)
    no_estimate = (np.zeros(3), np.zeros(3), np.zeros(2), np.zeros(3, bool))
    seq = []
    for _ in range(4):
        st = cfg.next_state(st, False, no_estimate, rot, 0.1)
        seq.append(st.window)
    assert seq == [tiles[0], cfg.view(), tiles[1], cfg.view()]
    # with the radar's altitude: the tiles only while the pad fits half a tile, else the view
    high = (np.array([0.0, 0.0, -30.0]), np.zeros(3), np.zeros(2), np.array([0, 0, 1], bool))
    low = (np.array([0.0, 0.0, -6.0]), np.zeros(3), np.zeros(2), np.array([0, 0, 1], bool))
    searching = cfg.next_state(st, False, high, rot, 0.1)  # st: the view after tiles 0, 1
    assert searching.window == tiles[2] and searching.search_step == 2
    assert cfg.next_state(searching, False, high, rot, 0.1).window == tiles[3]
    assert cfg.next_state(searching, False, low, rot, 0.1).window == cfg.view()
    # the pad found: 30 m above it, 2 m south of it, drifting north at 1 m/s
    found = (np.array([-2.0, 0.0, -30.0]), np.array([1.0, 0.0, 0.0]), np.full(2, 0.04), np.ones(3))
    st = cfg.next_state(st, True, found, rot, 0.1)
    assert st.window.kind == "track" and st.unseen == 0
    tan_forward = st.window.centre_tan[1]
    assert tan_forward == pytest.approx(1.9 / 30, abs=1.0 / cfg.fx_px)  # where it will be
    for k in range(1, 3):
        st = cfg.next_state(st, False, found, rot, 0.1)
        assert st.window.kind == "track" and st.unseen == k
    st = cfg.next_state(st, False, found, rot, 0.1)  # lost for lost_frames: search again
    assert st.window == tiles[0] and st.search_step == 0


def test_bad_roi_settings_name_the_key():
    with pytest.raises(CameraError, match="span_px"):
        roi_cfg(span_px=0.0)
    with pytest.raises(CameraError, match="too narrow"):
        RoiConfig.from_hfov(W, H, 40.0)
    with pytest.raises(CameraError, match="does not lie"):
        cut(np.zeros((H, W), np.uint8), RoiWindow(600, 0, 64, 500.0, 320.0, 240.0))
    with pytest.raises(CompanionError, match="camera_roi"):
        CompanionConfig(camera="udp:127.0.0.1:5600", camera_roi=True)
    with pytest.raises(CompanionError, match="camera_roi_span_px"):
        CompanionConfig(camera_roi=True, camera_roi_span_px=200.0)


# --------------------------------------------------------------------------- the policy


def test_roi_off_leaves_the_policy_as_it_was(policy):
    state = policy.initial_state()
    assert policy.roi is None and state.roi is None and roi_window(state) is None
    obs = level_observation(20.0)
    cmd, after = policy.act(obs, None, state)
    assert after.roi is None
    # ROI on a 128 px, 45° camera: the first window is the image itself, the same answer
    native = RoiConfig(128, 128, 64 / TAN_HALF, 63.5, 63.5)
    try:
        policy.roi = native
        on = policy.initial_state()
        assert isinstance(on.roi, RoiState)
        cmd_on, after_on = policy.act(obs, None, on)
    finally:
        policy.roi = None
    assert np.array_equal(cmd_on.rate_frd_rad_s, cmd.rate_frd_rad_s)
    assert cmd_on.thrust_norm == cmd.thrust_norm
    assert isinstance(after_on.roi, RoiState)


def test_an_in_process_flight_finds_the_pad_in_the_tiles_and_tracks_it(policy):
    """scenario_field: a 1 m pad from 30-50 m, beyond the 128 px image's reach; the 640 x 480
    simulator camera and the ROI find it and hold it."""
    from sitl_sim.env import LandingEnv
    from sitl_sim.full_res import FullResSimulator, camera_geometry

    env = LandingEnv(sim=sim_camera(), scenario="configs/scenario_field.toml")
    sim = env.simulator
    assert isinstance(sim, FullResSimulator)
    env.reset(seed=7, options={"episode_index": 0})
    try:
        policy.roi = RoiConfig(*camera_geometry(env.sim_config.camera), pad_m=1.0)
        state = policy.initial_state()
        sim.aim(roi_window(state))
        truth = sim.ground_truth()
        start_alt = -truth.pos_ned_m[2]
        kinds = []
        for frame in range(60):
            obs = sim.observe(frame_id=frame, truth=truth)
            assert obs.image.shape == (128, 128) and sim.full_frame.shape == (H, W)
            cmd, state = policy.act(obs, truth, state)
            sim.aim(roi_window(state))
            kinds.append(state.roi.window.kind)
            assert sim.step(cmd) is None
            truth = sim.ground_truth()
    finally:
        policy.roi = None
        env.close()
    assert start_alt > 40.0
    assert "tile" in kinds and kinds[-10:] == ["track"] * 10
    est = state.estimator
    assert np.linalg.norm(est.x[:2, 0] - truth.pos_ned_m[:2]) < 1.0
    # the pad's true pixel lies in the window the next frame is cut with
    from sitl_sim.physics.dynamics import quat_to_rotation

    w = state.roi.window
    body = quat_to_rotation(truth.quat_wxyz).T @ (-truth.pos_ned_m)
    u = w.cx_px + w.fx_px * body[1] / body[2]
    v = w.cy_px - w.fx_px * body[0] / body[2]
    assert w.x0 <= u <= w.x0 + w.side and w.y0 <= v <= w.y0 + w.side


def _hovering_video(tmp_path, renderer, altitude_m: float, frames: int, pad_m: float):
    """A lossless 640 x 480 video of ``frames`` renders ``altitude_m`` above the pad, 3 m north
    and 4 m west of it, opened as a RoiCameraSource; and the camera's (fx, cx, cy) in px."""
    import cv2

    from companion.roi import RoiCameraSource
    from sitl_sim.full_res import camera_geometry

    cam = sim_camera().camera
    path = tmp_path / "pad.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 10, (W, H))
    for _ in range(frames):
        frame = renderer.render([3.0, -4.0, -altitude_m], [1.0, 0.0, 0.0, 0.0], cam)
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    _, _, fx, cx, cy = camera_geometry(cam)
    source = RoiCameraSource(
        str(path), pad_m=pad_m, fx_px=fx, cx_px=cx, cy_px=cy, rate_hz=None, realtime=False
    )
    return source, (fx, cx, cy)


def test_a_real_camera_cuts_the_window_its_policy_asks_for(policy, tmp_path):
    """RoiCameraSource on a lossless video of 640 x 480 renders 40 m above the pad: the frames
    leave as 128 px windows, the first the 45° view, then around the pad."""
    from sitl_sim.render.render_fast import FastRenderer
    from tools.pad_info import resolve_pad

    renderer = FastRenderer(pad=resolve_pad("helipad_1m").scene_pad())
    source, (fx, cx, cy) = _hovering_video(tmp_path, renderer, 40.0, 25, pad_m=1.0)
    runtime = PolicyRuntime(policy, "shipped")
    try:
        assert (source.roi.width_px, source.roi.height_px) == (W, H)
        source.follow(runtime)
        assert policy.roi == source.roi
        windows, frames, steps = [], 0, 0
        while frames < 25:
            polled = source.poll()
            assert all(f.image.shape == (128, 128) for f in polled)
            frames += len(polled)
            if polled:  # the newest is answered, as the companion's loop does
                windows.append(roi_window(runtime.next_state()))
                obs = level_observation(40.0, time_s=0.1 * steps, image=polled[-1].image)
                assert runtime.step(obs, None).error is None
                steps += 1
    finally:
        policy.roi = None
        source.close()
    assert windows[0] == source.roi.view()
    last = roi_window(runtime.next_state())
    assert last.kind == "track" and last.side == round(fx / 40.0 * 128 / 24)  # 24 px of 128
    # the vehicle is 3 m north and 4 m west of the pad: the pad 0.1 right, 0.075 behind
    u, v = cx + fx * 4.0 / 40.0, cy + fx * 3.0 / 40.0
    assert abs(last.x0 + (last.side - 1) / 2 - u) < 8 and abs(last.y0 + (last.side - 1) / 2 - v) < 8


def test_landing_target_mode_tracks_through_the_window_its_tracker_asks_for(policy, tmp_path):
    """The same camera with the landing-target mode's tracker (no controller): the windows
    follow the tracker's estimate, and the target it would send is the pad's true offset."""
    from companion.landing_target import PadTracker
    from sitl_sim.render.render_fast import FastRenderer

    # the paper's pad, the shipped model's
    source, _ = _hovering_video(tmp_path, FastRenderer(), 60.0, 30, pad_m=4.0)
    tracker = PadTracker(policy)
    try:
        source.follow(tracker)
        tracker.reset()  # a flight starts (LandingTargetController) once the camera follows
        assert policy.roi == source.roi and roi_window(tracker.next_state()) == source.roi.view()
        frames, steps, result = 0, 0, None
        while frames < 30:
            polled = source.poll()
            frames += len(polled)
            if polled:
                obs = level_observation(60.0, time_s=0.1 * steps, image=polled[-1].image)
                result = tracker.step(obs)
                assert result.error is None
                steps += 1
    finally:
        policy.roi = None
        source.close()
    window = roi_window(tracker.next_state())
    assert window.kind == "track" and window.side < source.roi.view().side
    # the vehicle is 3 m north and 4 m west of the pad: the pad 3 m south, 4 m east of it
    assert result is not None and result.target_rel_ned_m is not None
    assert np.hypot(result.target_rel_ned_m[0] + 3.0, result.target_rel_ned_m[1] - 4.0) < 1.0, (
        result
    )


def test_camera_roi_is_a_landing_target_setting_too():
    cfg = CompanionConfig(camera="opencv:0", camera_roi=True, mode="landing-target")
    assert cfg.camera_roi and cfg.mode == "landing-target"


# --------------------------------------------------------------------------- the command


def test_pad_acquire_end_to_end(capsys):
    args = "pad acquire --pad helipad_1m --altitudes 15 45 --frames 3 --grounds nominal grass"
    code = main([*args.split(), "--json"])
    out = capsys.readouterr()
    assert code == 0, out.err
    res = json.loads(out.out)
    modes = res["modes"]
    assert res["camera"]["width_px"] == 640 and res["threshold"] == 0.9
    # the ROI holds the 1 m pad at 45 m, where the 45° crop of the same camera loses it
    assert modes["track"]["acquire_altitude_m"] == 45.0
    assert modes["crop"]["rows"][1]["detected"] < 0.5
    assert modes["track"]["bearing_error_deg_median"] < 0.3
    assert res["track_false_alarms"] == 0 and res["search"]["false_alarms"] == 0
    assert main(["pad", "acquire", "--grounds", "lava", "--json"]) != 0
