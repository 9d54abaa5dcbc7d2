"""Training pipeline: replay buffer, dataset from real logs, checkpoints, learning, geometry."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import episode_observation

from companion.contract import GroundTruth
from companion.policy_net import (
    CheckpointError,
    ControlLSTM,
    NetConfig,
    PerceptionCNN,
    load_networks,
    load_policy,
    position_from_bearing,
    save_checkpoint,
    untrained_policy,
)
from companion.runtime import level_observation
from training.dataset import DatasetError, load_episode
from training.replay import BufferedEpisode, ReplayBuffer
from training.train import (
    LabelGate,
    _shift,
    bearing_labels,
    privileged_episode,
    train_controller,
    vision_episode,
)


def _episode(name: str, n: int, offset: float = 0.0) -> BufferedEpisode:
    steps = np.arange(n, dtype=np.float32)[:, None]
    feats = np.repeat(steps + offset, 18, axis=1)
    labels = np.repeat(steps + offset, 4, axis=1)
    return BufferedEpisode(name, feats, labels)


# ----------------------------------------------------------------------------- replay buffer


def test_replay_buffer_fifo_and_contiguous_segments():
    buf = ReplayBuffer(capacity=3, segment_steps=25, seed=1)
    evicted = [buf.add(_episode(f"e{i}", 40 + i, offset=1000.0 * i)) for i in range(5)]
    assert len(buf) == 3
    assert [e.name for e in buf.episodes] == ["e2", "e3", "e4"]  # oldest went first
    assert evicted[:3] == [None, None, None] and evicted[3].name == "e0"
    feats, labels, mask = buf.sample(64)
    assert feats.shape == (64, 25, 18) and labels.shape == (64, 25, 4)
    assert np.all(mask == 1)
    # each row is 25 consecutive steps of one held episode
    diffs = np.diff(feats[:, :, 0], axis=1)
    assert np.all(diffs == 1.0)
    assert set(np.unique(feats[:, 0, 0] // 1000)) <= {2.0, 3.0, 4.0}


def test_replay_buffer_skips_short_episodes_and_is_seeded():
    a, b = ReplayBuffer(seed=7), ReplayBuffer(seed=7)
    for buf in (a, b):
        buf.add(_episode("short", 10))
        buf.add(_episode("long", 60, offset=500.0))
    fa, _, _ = a.sample(32)
    fb, _, _ = b.sample(32)
    assert np.array_equal(fa, fb)
    assert np.all(fa[:, 0, 0] >= 500.0)  # the 10-step episode is never eligible
    empty = ReplayBuffer()
    empty.add(_episode("tiny", 5))
    with pytest.raises(ValueError, match="no episode has 25 steps"):
        empty.sample(4)


def test_replay_buffer_burn_in_masks_the_warm_up():
    buf = ReplayBuffer(segment_steps=25, seed=3)
    buf.add(_episode("e", 200))
    feats, _labels, mask = buf.sample(200, burn_in_steps=50)
    assert feats.shape == (200, 75, 18)
    assert np.all(mask.sum(axis=1) == 25)
    for row in range(200):
        on = np.nonzero(mask[row])[0]
        assert np.all(np.diff(on) == 1)  # the segment is contiguous
        start = int(feats[row, on[0], 0])
        # burn-in is the same episode's preceding steps, as many as exist (<= 50)
        assert on[0] == min(start, 50)
        assert np.all(np.diff(feats[row, : on[-1] + 1, 0]) == 1.0)


def test_buffered_episode_rejects_misaligned_or_nan():
    with pytest.raises(ValueError, match="do not align"):
        BufferedEpisode("x", np.zeros((10, 18), np.float32), np.zeros((9, 4), np.float32))
    bad = np.zeros((10, 18), np.float32)
    bad[3, 2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        BufferedEpisode("x", bad, np.zeros((10, 4), np.float32))


def test_replay_buffer_weights_are_the_loss_mask():
    """A step's weight is its loss mask; an episode with no weight at all is never drawn."""
    w = np.zeros(60, np.float32)
    w[30:] = 1.0
    buf = ReplayBuffer(segment_steps=25, seed=4)
    buf.add(BufferedEpisode("half", _episode("h", 60).features, _episode("h", 60).labels, w))
    zero = _episode("z", 60, offset=1000.0)
    buf.add(BufferedEpisode("none", zero.features, zero.labels, np.zeros(60, np.float32)))
    feats, _labels, mask = buf.sample(300)
    assert np.all(feats[:, 0, 0] < 1000.0)  # "none" is never drawn
    assert np.array_equal(mask, (feats[:, :, 0] >= 30).astype(np.float32))
    with pytest.raises(ValueError, match="weights: expected"):
        BufferedEpisode("x", zero.features, zero.labels, np.full(60, 2.0, np.float32))
    with pytest.raises(ValueError, match="weights: expected"):
        BufferedEpisode("x", zero.features, zero.labels, np.ones(59, np.float32))


def test_a_step_of_weight_zero_teaches_nothing():
    """Two buffers that differ only in the labels of weight-0 steps train the same weights."""
    base = _episode("e", 80)
    w = (np.arange(80) % 3 != 0).astype(np.float32)
    wild = base.labels.copy()
    wild[w == 0] = 7.0  # a saturated dash to a pad the learner did not know of
    nets = []
    for labels in (base.labels, wild):
        buf = ReplayBuffer(segment_steps=25, seed=5)
        buf.add(BufferedEpisode("e", base.features / 80.0, labels / 80.0, w))
        torch.manual_seed(0)
        control = ControlLSTM(NetConfig(kind="privileged"))
        train_controller(control, buf, 20, batch_segments=8, seed=3)
        nets.append(control.state_dict())
    for k, v in nets[0].items():
        assert torch.equal(v, nets[1][k]), k


def test_label_gate_keeps_only_steps_whose_estimate_has_the_pad():
    gate = LabelGate()  # max(2 m, 10 % of the altitude); 1 m/s
    truth = np.array([[0, 0, -10.0], [0, 0, -10.0], [0, 0, -80.0], [0, 0, -80.0], [0, 0, -1.0]])
    est = truth + np.array([[1.5, 0, 0], [3.0, 0, 0], [7.0, 0, 0], [0, 9.0, 0], [0, 0, 1.9]])
    vel = np.zeros((5, 3))
    assert gate.weights(est, truth, vel, vel).tolist() == [1, 0, 1, 0, 1]
    est[0] = np.nan  # no estimate yet: the learner does not know where the pad is
    fast = vel.copy()
    fast[2] = [0.0, 1.5, 0.0]  # a pad that moves under an estimate that takes it as still
    assert gate.weights(est, truth, fast, vel).tolist() == [0, 0, 0, 0, 1]


def test_vision_episode_gates_the_labels_by_the_replayed_estimate(expert_logs):
    """The shipped model replayed on an expert flight has the pad after acquisition: those
    steps are learnt; the same flight with the truth moved 50 m has no step learnt."""
    policy = load_policy("models/visland_vision.pt")
    ep = load_episode(expert_logs[0], None, with_images=True)
    gated = vision_episode(policy, ep, LabelGate())
    plain = vision_episode(policy, ep)
    assert plain.weights is None
    assert np.array_equal(gated.features, plain.features)  # the gate only weighs
    assert gated.weights.mean() > 0.8, gated.weights.mean()
    moved = dataclasses.replace(ep, pos_ned_m=ep.pos_ned_m + np.array([50.0, 0.0, 0.0]))
    assert vision_episode(policy, moved, LabelGate()).weights.sum() == 0


# ----------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def expert_logs(tmp_path_factory) -> list[Path]:
    """Two real expert flights with camera, flown in process (about 3 s)."""
    from training.exec.rollout import RolloutSpec, log_name, run_episodes

    out = tmp_path_factory.mktemp("flights")
    run_episodes(RolloutSpec(policy="expert", seed=5, log_dir=str(out)), [0, 1], workers=1)
    return [out / log_name(5, i) for i in (0, 1)]


def test_episode_from_log_is_aligned_validated_and_cached(expert_logs, tmp_path):
    ep = load_episode(expert_logs[0], None, with_images=True, cache_dir=tmp_path)
    n = len(ep)
    assert n > 100 and ep.images.shape == (n, 128, 128)
    assert np.array_equal(ep.frame_id, np.arange(n))
    assert np.array_equal(ep.label, ep.flown)  # the expert flew it: its command is the label
    assert not ep.label.flags.writeable
    cached = load_episode(expert_logs[0], None, with_images=True, cache_dir=tmp_path)
    assert np.array_equal(cached.images, ep.images) and np.array_equal(cached.label, ep.label)
    assert any(tmp_path.glob("*.npz"))


def test_bad_logs_give_clear_errors(expert_logs, tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(DatasetError, match=r"junk\.mcap"):
        load_episode(junk)
    with pytest.raises(DatasetError, match="no such flight log"):
        load_episode(tmp_path / "missing.mcap")
    with pytest.raises(DatasetError, match="no such label file"):
        load_episode(expert_logs[0], tmp_path / "missing.labels.mcap")


def test_bearing_labels_match_the_rendered_pad(expert_logs):
    """The CNN's target geometry agrees with pybullet's image: the pad's centroid.

    In mono8 the pad's green is brighter than any ground pixel; the cross's holes in it are
    symmetric, so the bright pixels' centroid is the pad centre while the pad is in full view.
    """
    from companion.flightlog import read_log

    ep = load_episode(expert_logs[0], None, with_images=True)
    labels = bearing_labels(ep.pos_ned_m, ep.quat_wxyz, 45.0)
    focal = 64 / math.tan(math.radians(22.5))
    log = read_log(expert_logs[0])
    assert log.topic("/camera/image")
    for t in (0, len(ep) // 3):
        img = ep.images[t].astype(float)
        rows, cols = np.nonzero(img > 130)
        assert rows.size > 20
        assert labels[t, 2] == 1.0
        assert abs(cols.mean() - (64 + focal * labels[t, 0])) < 2.5
        assert abs(rows.mean() - (64 - focal * labels[t, 1])) < 2.5


def test_shift_augmentation_moves_the_label_with_the_image():
    rng = np.random.default_rng(0)
    img = torch.zeros(8, 128, 128)
    img[:, 60:68, 60:68] = 255.0  # a blob at the centre
    y = torch.zeros(8, 3)
    y[:, 2] = 1
    focal = 64 / math.tan(math.radians(22.5))
    out, y2 = _shift(img, y, rng, 30, focal, math.tan(math.radians(22.5)))
    for i in range(8):
        rows, cols = np.nonzero(out[i].numpy() > 128)
        assert abs(cols.mean() - 63.5 - focal * float(y2[i, 0])) < 0.6
        assert abs(rows.mean() - 63.5 + focal * float(y2[i, 1])) < 0.6


def test_position_from_bearing_inverts_the_projection():
    from companion.policy_net import rotation_zyx

    rng = np.random.default_rng(2)
    for _ in range(20):
        att = rng.uniform(-0.4, 0.4, 3)
        att[2] = rng.uniform(-math.pi, math.pi)
        pos = np.array([*rng.uniform(-8, 8, 2), -rng.uniform(2, 90)])
        rot = rotation_zyx(*att)
        rel = rot.T @ (-pos)
        rng_m = -pos[2] / rot[2, 2]
        est = position_from_bearing(rel[1] / rel[2], rel[0] / rel[2], att, rng_m)
        assert np.allclose(est, pos, atol=1e-9)
    assert position_from_bearing(0.0, 0.0, np.zeros(3), math.nan) is None


# ----------------------------------------------------------------------------- learning


def _fit(episodes: list[BufferedEpisode], steps: int, seed: int) -> ControlLSTM:
    torch.manual_seed(seed)
    control = ControlLSTM(NetConfig(kind="privileged"))
    buf = ReplayBuffer(seed=seed)
    for e in episodes:
        buf.add(e)
    train_controller(control, buf, steps, batch_segments=16, seed=seed, burn_in_steps=10)
    return control


def _loss(control: ControlLSTM, ep: BufferedEpisode) -> float:
    from training.train import COMMAND_SCALE

    with torch.no_grad():
        pred, _ = control(torch.from_numpy(ep.features)[None])
    return float((((pred[0].numpy() - ep.labels) / COMMAND_SCALE) ** 2).mean())


def test_training_helps_and_is_deterministic(expert_logs):
    """Statistical check on a tiny budget: BC on one flight lowers the error on the other."""
    eps = [privileged_episode(load_episode(p)) for p in expert_logs]
    before = []
    after = []
    for seed in (0, 1, 2):
        torch.manual_seed(seed)
        untrained = ControlLSTM(NetConfig(kind="privileged"))
        before.append(_loss(untrained, eps[1]))
        after.append(_loss(_fit([eps[0]], 150, seed), eps[1]))
    assert max(after) < 0.5 * min(before), (before, after)
    a, b = _fit([eps[0]], 30, 9), _fit([eps[0]], 30, 9)
    for (ka, va), (_, vb) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert torch.equal(va, vb), ka


def test_vision_features_match_the_policy_in_flight(expert_logs):
    """Training's batched features equal what LearnedPolicy.act computes step by step."""
    policy = untrained_policy(seed=3)
    ep = load_episode(expert_logs[0], None, with_images=True)
    batched = vision_episode(policy, ep).features
    state = policy.initial_state()
    for t in range(30):
        time_s = float(ep.time_s[t])
        obs = episode_observation(ep, t, image_time_s=time_s, time_s=time_s)
        feats, state = policy.features(obs, None, state)
        assert np.allclose(feats, batched[t], atol=1e-5), t


# ----------------------------------------------------------------------------- checkpoints


def test_checkpoint_round_trip_and_errors(tmp_path):
    cfg = NetConfig(kind="vision")
    torch.manual_seed(0)
    control, cnn = ControlLSTM(cfg), PerceptionCNN(cfg)
    path = save_checkpoint(tmp_path / "p.pt", cfg, control, cnn, {"data": ["a.mcap"]})
    policy = load_policy(path)
    assert policy.metadata == {"data": ["a.mcap"]} and not policy.privileged
    x = torch.randn(2, 7, 18)
    with torch.no_grad():
        assert torch.equal(control(x)[0], policy.control(x)[0])
        img = torch.randint(0, 255, (2, 128, 128), dtype=torch.uint8)
        assert torch.equal(cnn(img), policy.perception(img))

    raw = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(CheckpointError, match=r"cut\.pt"):
        load_policy(tmp_path / "cut.pt")
    (tmp_path / "text.pt").write_text("hello")
    with pytest.raises(CheckpointError, match="not a readable"):
        load_policy(tmp_path / "text.pt")
    torch.save({"format": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not a visland policy"):
        load_policy(tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_policy(tmp_path / "missing.pt")
    # weights of another size
    small = NetConfig(kind="privileged", lstm_hidden=16)
    save_checkpoint(tmp_path / "small.pt", small, ControlLSTM(small), None, {})
    blob = torch.load(tmp_path / "small.pt", weights_only=True)
    blob["net_config"]["lstm_hidden"] = 64
    torch.save(blob, tmp_path / "mismatch.pt")
    with pytest.raises(CheckpointError, match="do not fit"):
        load_networks(tmp_path / "mismatch.pt")
    # NaN weights
    nan_ctl = ControlLSTM(small)
    with torch.no_grad():
        next(nan_ctl.parameters())[0, 0] = float("nan")
    save_checkpoint(tmp_path / "nan.pt", small, nan_ctl, None, {})
    with pytest.raises(CheckpointError, match="non-finite"):
        load_policy(tmp_path / "nan.pt")


def test_policy_outputs_respect_command_ranges_and_refuse_bad_input():
    policy = untrained_policy(seed=1)
    obs = level_observation(range_m=40.0, grey=90, accel_frd_m_s2=np.array([0.0, 0.0, -9.8]))
    state = policy.initial_state()
    for _ in range(5):
        cmd, state = policy.act(obs, None, state)
        assert 0.0 <= cmd.thrust_norm <= 1.0
        assert np.all(np.abs(cmd.rate_frd_rad_s) <= np.array([3.5, 3.5, 1.5]) + 1e-6)
    priv = untrained_policy(seed=1, privileged=True)
    with pytest.raises(ValueError, match="needs ground truth"):
        priv.act(obs, None, priv.initial_state())
    gt = GroundTruth(
        0.0, np.array([1.0, 2.0, -30.0]), np.array([np.nan, 0, 0]), np.eye(4)[0], np.zeros(3)
    )
    with pytest.raises(ValueError, match="not finite"):
        priv.act(obs, gt, priv.initial_state())


def test_train_stage_without_its_prerequisite_is_a_clear_cli_error(tmp_path, capsys):
    from tools.cli import main

    assert main(["train", "bc", "--run", str(tmp_path / "run"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "stage 'collect'" in err and "has not finished" in err


# ----------------------------------------------------------------------------- robustness


def test_pose_sampled_frames_show_the_pad_where_the_labels_say(tmp_path):
    """Rendered by the flying camera at sampled poses; the in-view pad's bright pixels sit
    around the labelled bearing, out-of-view samples are labelled invisible, and the cache
    reloads the same frames."""
    from sitl_sim.config import load_sim
    from training.perception_data import PoseSampling, render_pose_frames, sample_poses

    cam = load_sim().camera
    sampling = PoseSampling(altitude_m=(15.0, 40.0))
    pos, quat = sample_poses(400, 3, cam.fov_deg, sampling)
    labels = bearing_labels(pos, quat, cam.fov_deg)
    assert 0.7 < labels[:, 2].mean() < 0.9  # in_view_fraction 0.8
    assert np.all((-pos[:, 2] >= 15.0) & (-pos[:, 2] <= 40.0))
    images, pos2, quat2 = render_pose_frames(24, 3, cam, cache_dir=tmp_path, sampling=sampling)
    assert images.shape == (24, 128, 128) and images.dtype == np.uint8
    labels = bearing_labels(pos2, quat2, cam.fov_deg)
    focal = 64 / math.tan(math.radians(22.5))
    checked = 0
    for img, lab in zip(images, labels, strict=True):
        col, row = 64 + focal * lab[0], 64 - focal * lab[1]
        if lab[2] and 12 < col < 116 and 12 < row < 116:  # the whole pad in view
            rows, cols = np.nonzero(img > 130)
            assert rows.size > 10
            assert abs(cols.mean() - col) < 3.0 and abs(rows.mean() - row) < 3.0
            checked += 1
    assert checked >= 5
    again, _, _ = render_pose_frames(24, 3, cam, cache_dir=tmp_path, sampling=sampling)
    assert np.array_equal(again, images)


def test_far_off_samples_are_bare_ground_and_leave_the_rest_as_they_were():
    """``away_fraction``: that share of the poses 40-300 m from the pad, none with it in view
    (label 0, and no pad pixels); with 0 the draws, and a cache's key, are as before it
    existed."""
    from sitl_sim.config import load_sim
    from training.perception_data import PoseSampling, render_pose_frames, sample_poses

    cam = load_sim().camera
    plain = PoseSampling(altitude_m=(15.0, 40.0))
    before = sample_poses(200, 3, cam.fov_deg, plain)
    again = sample_poses(200, 3, cam.fov_deg, dataclasses.replace(plain, away_m=(10.0, 20.0)))
    assert all(np.array_equal(a, b) for a, b in zip(before, again, strict=True))
    assert "away_fraction" not in plain.key()
    # (the other samples look at least 0.1 down their ray: <= 398 m off at 40 m up)
    mixed = dataclasses.replace(plain, away_fraction=0.25, away_m=(400.0, 500.0))
    pos, quat = sample_poses(800, 3, cam.fov_deg, mixed)
    far = np.hypot(pos[:, 0], pos[:, 1]) >= 400.0
    assert 0.2 < far.mean() < 0.3 and np.all(np.hypot(pos[far, 0], pos[far, 1]) <= 500.0)
    pos, quat = sample_poses(400, 4, cam.fov_deg, dataclasses.replace(plain, away_fraction=1.0))
    off = np.hypot(pos[:, 0], pos[:, 1])
    assert np.all((off >= 40.0) & (off <= 300.0))
    assert not bearing_labels(pos, quat, cam.fov_deg)[:, 2].any()
    bare = dataclasses.replace(plain, away_fraction=1.0)
    images, _, _ = render_pose_frames(16, 3, cam, sampling=bare)
    assert (images > 130).sum(axis=(1, 2)).max() < 10  # the pad's bright cross is nowhere
    assert mixed.key()["away_fraction"] == 0.25


def test_estimator_gates_a_wild_fix_and_reacquires_after_repeated_ones():
    from companion.policy_net import PadEstimator

    cfg = NetConfig()
    est = PadEstimator(cfg)
    level, hover = np.zeros(3), np.array([0.0, 0.0, -9.80665])
    s = est.initial_state()
    for _ in range(20):  # settle on a fix 2 m north at 40 m
        s = est.step(s, np.array([2.0, 0.0, -40.0]), True, level, hover)
    assert abs(s.x[0, 0] - 2.0) < 0.05
    # one CNN answer 30 m off (a tilted view without the pad): refused, altitude still updated
    s = est.step(s, np.array([-28.0, 5.0, -39.0]), True, level, hover)
    assert abs(s.x[0, 0] - 2.0) < 0.1 and s.rejected == 1
    assert -39.9 < s.x[2, 0] < -39.0  # the radar altitude is not gated
    # a good fix clears the count
    s = est.step(s, np.array([2.0, 0.0, -39.0]), True, level, hover)
    assert s.rejected == 0
    # the same far answer again and again: the prediction was wrong, re-acquire from the fix
    for _ in range(cfg.gate_reset_steps):
        s = est.step(s, np.array([-28.0, 5.0, -39.0]), True, level, hover)
    assert abs(s.x[0, 0] + 28.0) < 1e-9 and abs(s.x[1, 0] - 5.0) < 1e-9 and s.rejected == 0
    # with the gate off every fix is taken
    off = PadEstimator(NetConfig(gate_sigma=0.0))
    s = off.initial_state()
    for _ in range(20):
        s = off.step(s, np.array([2.0, 0.0, -40.0]), True, level, hover)
    s = off.step(s, np.array([-28.0, 5.0, -39.0]), True, level, hover)
    assert s.x[0, 0] < 0.0


def test_redo_reruns_a_stage_and_drops_the_later_records(tmp_path):
    """`visland train STAGE --redo` and a run folder made before a profile key existed."""
    import json

    from training.pipeline import PipelineError, run_pipeline
    from training.profiles import PROFILES

    run = tmp_path / "run"
    (run / "stages").mkdir(parents=True)
    old = PROFILES["quick"].to_dict()
    del old["perception_pose_frames"]  # as written by an older version
    (run / "profile.json").write_text(json.dumps({"profile": old, "scenario": None}))
    for stage in ("perception", "vision", "eval"):
        (run / "stages" / f"{stage}.json").write_text("{}")
    # 'vision' needs 'dagger', which never ran: the redo removes vision+eval, then stops there
    with pytest.raises(PipelineError, match="stage 'dagger'"):
        run_pipeline(run, "quick", stages=("vision",), progress=False, redo="vision")
    assert (run / "stages" / "perception.json").exists()
    assert not (run / "stages" / "vision.json").exists()
    assert not (run / "stages" / "eval.json").exists()
    prof = json.loads((run / "profile.json").read_text())
    assert prof["profile"]["perception_pose_frames"] == PROFILES["quick"].perception_pose_frames
    assert prof["upgraded"][0]["keys"] == ["perception_pose_frames"]
    # a key that differs (not merely missing) is still another run
    prof["profile"]["bc_steps"] += 1
    (run / "profile.json").write_text(json.dumps(prof))
    with pytest.raises(PipelineError, match="another profile"):
        run_pipeline(run, "quick", stages=("vision",), progress=False)


def test_a_finished_run_takes_new_estimator_settings_and_flies_vision_and_eval_again(tmp_path):
    """Only the estimator's settings differ: the trained stages stay, vision and eval lose
    their records (they fly with the estimator), profile.json says what changed; any other
    difference is still another run."""
    import json
    from dataclasses import replace

    from training.profiles import ESTIMATOR_KEYS, PROFILES, PipelineError
    from training.run_folder import Run

    assert "visibility_threshold" in ESTIMATOR_KEYS and "hover_input" not in ESTIMATOR_KEYS
    run = tmp_path / "run"
    (run / "stages").mkdir(parents=True)
    quick = PROFILES["quick"]
    (run / "profile.json").write_text(json.dumps({"profile": quick.to_dict(), "scenario": None}))
    for stage in ("dagger", "perception", "vision", "eval"):
        (run / "stages" / f"{stage}.json").write_text("{}")
    Run(run, replace(quick, visibility_threshold=0.9), progress=False).close()
    assert sorted(p.stem for p in (run / "stages").iterdir()) == ["dagger", "perception"]
    prof = json.loads((run / "profile.json").read_text())
    assert prof["profile"]["visibility_threshold"] == 0.9
    change = prof["estimator_changed"][0]["keys"]
    assert change == {"visibility_threshold": {"from": 0.5, "to": 0.9}}
    # the same settings again: nothing more is removed or recorded
    (run / "stages" / "vision.json").write_text("{}")
    Run(run, replace(quick, visibility_threshold=0.9), progress=False).close()
    assert (run / "stages" / "vision.json").exists()
    assert len(json.loads((run / "profile.json").read_text())["estimator_changed"]) == 1
    # a network key with it: another run, and nothing is touched
    with pytest.raises(PipelineError, match="another profile"):
        Run(run, replace(quick, visibility_threshold=0.8, hover_input=True), progress=False)
    assert (run / "stages" / "vision.json").exists()
    # an estimator key the run's profile.json predates enters at its default (the behaviour
    # the run had): a new value is a change like any other
    prof = json.loads((run / "profile.json").read_text())
    del prof["profile"]["unsure_threshold"]
    (run / "profile.json").write_text(json.dumps(prof))
    Run(run, replace(quick, visibility_threshold=0.9, unsure_threshold=0.5), progress=False).close()
    assert not (run / "stages" / "vision.json").exists()
    prof = json.loads((run / "profile.json").read_text())
    assert prof["upgraded"][-1]["keys"] == ["unsure_threshold"]
    change = prof["estimator_changed"][-1]["keys"]
    assert change == {"unsure_threshold": {"from": None, "to": 0.5}}
    assert prof["profile"]["unsure_threshold"] == 0.5


def test_an_estimator_ablation_starts_from_another_runs_trained_stages(tmp_path):
    """``visland pipeline --from RUN``: a new run folder whose profile differs from RUN's only
    in estimator settings (or in how the vision stage learns) takes RUN's records of collect
    through perception (not vision or eval) and says so in profile.json; anything else is
    refused with the keys named, and a refused start leaves no record behind."""
    import json
    from dataclasses import replace

    from training.profiles import PROFILES, PipelineError
    from training.report.results import _started_from
    from training.run_folder import Run

    quick = PROFILES["quick"]
    src = tmp_path / "src"
    (src / "stages").mkdir(parents=True)
    (src / "profile.json").write_text(json.dumps({"profile": quick.to_dict(), "scenario": None}))
    for stage in ("collect", "bc", "dagger", "dagger_r0", "perception", "vision", "eval"):
        (src / "stages" / f"{stage}.json").write_text(json.dumps({"stage": stage}))
    run = Run(tmp_path / "abl", replace(quick, visibility_threshold=0.9), progress=False)
    try:
        taken = run.start_from(src)
    finally:
        run.close()
    assert sorted(taken) == ["bc", "collect", "dagger", "dagger_r0", "perception"]
    got = sorted(p.stem for p in (tmp_path / "abl" / "stages").iterdir())
    assert got == ["bc", "collect", "dagger", "dagger_r0", "perception"]
    prof = json.loads((tmp_path / "abl" / "profile.json").read_text())
    assert prof["started_from"]["run"] == str(src)
    assert _started_from(tmp_path / "abl") == str(src)
    assert _started_from(src) is None
    again = Run(tmp_path / "abl", replace(quick, visibility_threshold=0.9), progress=False)
    with pytest.raises(PipelineError, match="needs a new run folder"):
        again.start_from(src)
    again.close()
    # how the vision stage learns may differ too: the stages taken do not read it
    gated = replace(quick, vision_label_gate=True, vision_truth_inputs=True, vision_rounds=4)
    vis = Run(tmp_path / "vis", gated, progress=False)
    try:
        assert sorted(vis.start_from(src)) == sorted(taken)
    finally:
        vis.close()
    # how the CNN learns may differ: the run takes the stages before perception, trains the rest
    cnn = Run(tmp_path / "cnn", replace(quick, perception_site_share=0.5), progress=False)
    try:
        assert sorted(cnn.start_from(src)) == ["bc", "collect", "dagger", "dagger_r0"]
        assert not cnn.record_path("perception").exists()
    finally:
        cnn.close()
    other = Run(tmp_path / "net", replace(quick, bc_steps=quick.bc_steps + 1), progress=False)
    with pytest.raises(PipelineError, match="differs in bc_steps"):
        other.start_from(src)
    (src / "stages" / "perception.json").unlink()
    partial = Run(tmp_path / "partial", quick, progress=False)
    with pytest.raises(PipelineError, match="stages perception have not finished"):
        partial.start_from(src)
    assert not any((tmp_path / "partial" / "stages").iterdir())
    other.close()
    partial.close()


def test_vision_starts_from_every_privileged_controller_that_landed(tmp_path):
    """Privileged validation cannot tell BC and DAgger controllers apart (millimetres for
    all), so each one that landed every flight becomes a vision candidate."""
    from training.profiles import PROFILES
    from training.run_folder import Run
    from training.stage_records import DaggerRecord, ValidationScore
    from training.stages.vision import privileged_controllers

    def finish_dagger(scores: list[ValidationScore]) -> None:
        first = scores[0].checkpoint
        run.finish(
            DaggerRecord(
                "dagger",
                run.commit,
                checkpoint=first,
                selected=first,
                validation=tuple(scores),
                rounds=2,
            )
        )

    run = Run(tmp_path / "run", PROFILES["quick"], progress=False, say=lambda _: None)
    try:
        records = []
        for i, (name, success) in enumerate((("bc", 1.0), ("dagger_r0", 0.0), ("dagger_r1", 1.0))):
            net = untrained_policy(seed=i, privileged=True)
            path = save_checkpoint(
                run.root / "checkpoints" / f"{name}.pt", net.config, net.control, None, {}
            )
            records.append(ValidationScore(str(path), 0.0, 0.0, success, 0.0))
        finish_dagger(records)
        cfg = run.net_config("vision")
        got = privileged_controllers(run, cfg)
        assert [name for name, _ in got] == ["bc", "dagger_r1"]
        _, r1, _, _ = load_networks(records[2].checkpoint)
        for a, b in zip(got[1][1].state_dict().values(), r1.state_dict().values(), strict=True):
            assert torch.equal(a, b)
        # none landed: all of them (validation decides with the camera)
        finish_dagger([dataclasses.replace(rec, success_rate=0.0) for rec in records])
        assert len(privileged_controllers(run, cfg)) == 3
    finally:
        run.close()


def test_a_moving_pad_episode_is_relative_to_the_pad(tmp_path):
    """On a rover the controller learns from (and the CNN's labels come from) the vehicle's
    state relative to the pad, as the vision estimator estimates it; not the world position,
    which on a moving pad would teach it to land where the pad was at the origin."""
    from companion.contract.records import GroundTruthRecord
    from companion.flightlog import read_log
    from training.exec.rollout import RolloutSpec, log_name, run_episodes

    spec = RolloutSpec(
        policy="expert",
        seed=5,
        scenario="configs/sites/rover_slow.toml",
        render_camera=False,
        log_dir=str(tmp_path),
    )
    (outcome,) = run_episodes(spec, [0], workers=1)
    assert outcome.result.success
    path = tmp_path / log_name(5, 0)
    ep = load_episode(path)
    truth = [GroundTruthRecord.from_dict(m) for m in read_log(path).topic("/groundtruth/state")]
    by_frame = {r.frame_id: r for r in truth}
    rows = [by_frame[int(f)] for f in ep.frame_id]
    world = np.array([r.pos_ned_m for r in rows])
    pad = np.array([r.pad_pos_ned_m for r in rows])
    vel = np.array([r.vel_ned_m_s for r in rows]) - np.array([r.pad_vel_ned_m_s for r in rows])
    assert np.array_equal(ep.pos_ned_m, world - pad) and np.array_equal(ep.vel_ned_m_s, vel)
    assert np.linalg.norm(pad[-1, :2] - pad[0, :2]) > 5.0  # the rover drove off
    assert np.linalg.norm(ep.pos_ned_m[-1, :2]) < 1.0  # landed on it...
    assert np.linalg.norm(world[-1, :2]) > 5.0  # ...far from where it started
