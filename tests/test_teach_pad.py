"""Teaching a pad (``visland pipeline --pad PADFILE --from MODEL``, ``training.pad_teach``): the
envelope rule where training reads it, the pad's suite held to the code, pose frames that show the
worlds' pad, the derived worlds, one pad run end to end on a tiny budget from the shipped model
(the pad in its frames, the controller kept, the CNN retrained, ``visland ship`` writing
``visland_vision_<pad>.pt`` and its card) and each bad input's error."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import scenario_with

from companion.files import sha256_file
from companion.policy_net import load_networks
from sitl_sim.config import load_sim
from sitl_sim.errors import ConfigError
from sitl_sim.render import pads as pads_module
from sitl_sim.render.pad_section import PadConfig
from sitl_sim.scenario import load_scenario
from sitl_sim.world import episode_world
from tools.cli import main
from training.pad_teach import PadMetrics, pad_suite_text, pad_worlds, teach_pad
from training.perception_data import PoseSampling, render_pose_frames
from training.pipeline import run_pipeline
from training.profiles import PROFILES, PipelineError
from training.provenance import REPO
from training.reports import SuiteReport
from training.seeds import EVAL_SEED
from training.suite import load_suite
from training.train import bearing_labels
from training.worlds import single_world

SHIPPED = REPO / "models" / "visland_vision.pt"
HELIPAD = REPO / "configs" / "pads" / "helipad_1m.toml"

# the robust profile (the shipped model's network) on a budget a test can fly: 512 pose frames,
# one epoch, one validation flight per world, two episodes per suite condition, no DAgger round,
# 128 close frames labelled by the shipped CNN
TINY = replace(
    PROFILES["robust"],
    pad_pose_frames=512,
    pad_perception_epochs=1,
    validation_episodes=4,
    eval_episodes=2,
    vision_rounds=0,
    workers=1,
    pad_close_fraction=0.25,
)


def run(capsys, *argv: str) -> tuple[int, str, str]:
    """``visland ARGV`` in this process: (exit code, stdout, stderr)."""
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def centre_luma(images: np.ndarray, pos: np.ndarray, quat: np.ndarray) -> list[float]:
    """The median grey level of 3 x 3 pixels around where the pad's centre appears."""
    cam = load_sim().camera
    focal = 0.5 * cam.width_px / math.tan(math.radians(cam.fov_deg) / 2)
    out = []
    for image, (tr, tf, _) in zip(images, bearing_labels(pos, quat, cam.fov_deg), strict=True):
        col = round(cam.width_px / 2 - 0.5 + focal * tr)
        row = round(cam.height_px / 2 - 0.5 - focal * tf)
        if 1 <= row < cam.height_px - 1 and 1 <= col < cam.width_px - 1:
            out.append(float(np.median(image[row - 1 : row + 2, col - 1 : col + 2])))
    return out


# --------------------------------------------------------------------------- the envelope


def test_envelope_rule_lives_in_pads_and_pad_info_uses_it():
    import tools.pad_info as pad_info

    for name in ("ACQUIRE_PX", "REFERENCE", "START_FRACTION", "start_altitudes_m"):
        assert getattr(pad_info, name) is getattr(pads_module, name)
    assert pads_module.start_altitudes_m(4.0) == pytest.approx((75.0, 100.0))
    teach = teach_pad(HELIPAD)
    assert teach.record.start_altitude_m == pytest.approx((18.75, 25.0))
    assert teach.scale == pytest.approx(0.25)
    assert teach.design_text == "helipad_1m"  # a shipped pad by its name
    assert teach_pad("helipad_1m").record == teach.record


def test_helipad_suite_file_is_what_the_code_writes():
    text = (REPO / "configs" / "suites" / "helipad_1m.toml").read_text()
    assert text == pad_suite_text(teach_pad(HELIPAD)), (
        "configs/suites/helipad_1m.toml is stale: python -m training.pad_teach "
        "configs/pads/helipad_1m.toml > configs/suites/helipad_1m.toml"
    )
    suite = load_suite(REPO / "configs" / "suites" / "helipad_1m.toml")
    standard_suite = load_suite(REPO / "configs" / "suites" / "standard.toml")
    standard = {c.name: c.scenario for c in standard_suite.conditions}
    assert [c.name for c in suite.conditions] == [
        "nominal",
        "low_sun",
        "unseen_terrain",
        "wind_moderate_gusts",
    ]
    assert (suite.episodes, suite.seed) == (50, EVAL_SEED)
    for c in suite.conditions:
        assert c.scenario.altitude_m == pytest.approx((18.75, 25.0))
        assert [d.name for d in c.scenario.pad.designs] == ["helipad_1m"]
        base = standard[c.name]  # everything else as the standard suite's condition
        assert c.scenario.north_east_m == base.north_east_m
        assert c.scenario.wind == base.wind
        assert (c.scenario.visual is None) == (base.visual is None)
        if base.visual is not None:
            assert c.scenario.visual.terrain == base.visual.terrain
            assert c.scenario.visual.texture_seed == base.visual.texture_seed
            assert c.scenario.visual.sun_elevation_deg == base.visual.sun_elevation_deg


# --------------------------------------------------------------------------- pose frames


def test_pose_frames_show_the_worlds_pad(tmp_path):
    cam = load_sim().camera
    low = PoseSampling(
        altitude_m=(2.0, 3.0), in_view_fraction=1.0, level_fraction=1.0, level_tilt_deg=3.0
    )
    paper, pos, quat = render_pose_frames(24, 3, cam, cache_dir=tmp_path, sampling=low)
    heli, pos_h, quat_h = render_pose_frames(
        24, 3, cam, cache_dir=tmp_path, sampling=low, pads=(PadConfig(design=("helipad_1m",)),)
    )
    assert np.array_equal(pos, pos_h) and np.array_equal(quat, quat_h)  # same poses
    # at the pad's centre: the paper pad's red cross (grey ~75), the helipad's white H (~230)
    assert max(centre_luma(paper, pos, quat)) < 120
    assert min(centre_luma(heli, pos, quat)) > 200
    # a section without pads renders as before, from the cache made before (its key unchanged)
    assert np.array_equal(render_pose_frames(24, 3, cam, sampling=low, pads=(None,))[0], paper)
    with np.load(tmp_path / "poses_s3_n24.npz") as z:
        assert "helipad_1m" in str(z["key"])  # the last render (the helipad) is the cache


def test_pose_frames_show_the_site_that_carries_the_pad(tmp_path):
    """In a rover world the frames show the pad on the rover's roof with its cab beside it (a
    CNN never shown the cab takes pad and cab for one and answers towards the cab); the labels
    still point at the pad's centre (the red cross, seen through the roof's height); on a steep
    slope no camera sits under the hillside, and a lifted pose keeps its bearing."""
    cam = load_sim().camera
    low = PoseSampling(
        altitude_m=(6.0, 12.0), in_view_fraction=1.0, level_fraction=1.0, level_tilt_deg=3.0
    )
    rover = load_scenario("configs/sites/rover_slow.toml")
    flat, pos, quat = render_pose_frames(24, 3, cam, sampling=low, visuals=(rover.visual,))
    site, pos_s, quat_s = render_pose_frames(
        24, 3, cam, cache_dir=tmp_path, sampling=low, visuals=(rover.visual,),
        pads=(rover.pad,), terrains=(rover.terrain,),
    )  # fmt: skip
    assert np.array_equal(pos, pos_s) and np.array_equal(quat, quat_s)  # none under ground
    assert max(centre_luma(site, pos_s, quat_s)) < 120  # the cross where the label says
    # the cab, the wheels and the ground 1.2-1.8 m lower: the frames are not the flat ones
    changed = np.abs(site.astype(int) - flat.astype(int)).mean(axis=(1, 2))
    assert np.all(changed > 2.0), changed
    with np.load(tmp_path / "poses_s3_n24.npz") as z:
        assert "rover" in str(z["key"])  # the site is in the cache key
    hill = scenario_with(terrain={"slope_deg": [25.0, 25.0]})
    near = PoseSampling(altitude_m=(1.0, 2.0), in_view_fraction=0.0, out_of_view_tan=1.0)
    _, rel, q = render_pose_frames(24, 3, cam, sampling=near)
    images, lifted, q2 = render_pose_frames(
        24, 3, cam, sampling=near, terrains=(hill.terrain,), pads=(hill.pad,)
    )
    assert np.array_equal(q, q2) and images.shape[0] == 24
    moved = np.any(lifted != rel, axis=1)
    assert moved.any()  # some poses beside the pad were inside the hillside
    site = episode_world(hill, 3, 0).site
    for p in lifted + site.pad_pose(0.0).position_ned:
        assert -p[2] - site.surface_height(float(p[0]), float(p[1]), 0.0) >= 0.5 - 1e-9
    assert np.allclose(
        bearing_labels(lifted, q2, cam.fov_deg)[:, :2], bearing_labels(rel, q, cam.fov_deg)[:, :2]
    )


def test_pad_worlds_scale_altitudes_keep_files_and_seeds(tmp_path):
    teach = teach_pad(HELIPAD)
    source = single_world(str(REPO / "configs" / "scenario_ground_field_grass.toml"))
    worlds = pad_worlds(source, teach, tmp_path / "worlds")
    (w,) = worlds.worlds
    assert (w.name, w.share, w.seed_offset) == ("scenario", 1.0, 0)
    assert w.scenario.altitude_m == pytest.approx((18.75, 25.0))
    assert w.scenario.north_east_m == source.worlds[0].scenario.north_east_m
    assert [d.path for d in w.scenario.pad.designs] == [HELIPAD.resolve()]
    # the ground picture, named relative to the scenario file there, still resolves here
    assert w.scenario.visual.ground_paths == source.worlds[0].scenario.visual.ground_paths
    # the default scenario (no file): the paper's 75-100 m become the helipad's 18.75-25 m
    default = pad_worlds(single_world(None), teach, tmp_path / "default")
    assert default.worlds[0].scenario.altitude_m == pytest.approx((18.75, 25.0))


def test_pad_worlds_keep_the_carrier_of_a_carried_pad(tmp_path):
    """A rover's or a deck's pad, taught, is still carried: only the design changes (the paper's
    pad taught in the sites' worlds, profile ``robust_sites_teach``, trains on rovers and
    decks); the teach's bare-ground frames lie at distances scaled with the pad."""
    from training.stages.teach import pose_sampling

    teach = teach_pad(HELIPAD)
    for site in ("rover_fast", "deck_moderate"):
        source = single_world(str(REPO / "configs" / "sites" / f"{site}.toml"))
        (w,) = pad_worlds(source, teach, tmp_path / site).worlds
        before = source.worlds[0].scenario.pad
        assert [d.name for d in w.scenario.pad.designs] == ["helipad_1m"]
        assert w.scenario.pad.motion == before.motion != "static"
        for key in ("height_m", "speed_m_s", "turn_rate_deg_s", "heave_m", "roll_deg"):
            assert getattr(w.scenario.pad, key) == getattr(before, key), key
    sampling = pose_sampling(teach, 0.05)
    assert sampling.away_fraction == 0.05
    assert sampling.away_m == pytest.approx((10.0, 75.0))  # 40-300 m x 0.25
    assert "away_m" not in pose_sampling(teach).key()  # no bare ground: the cache key as before
    assert PROFILES["robust_sites_teach"].perception_away_fraction == 0.05


def test_the_robust_teach_shows_bare_ground_and_older_runs_keep_theirs():
    """``visland pipeline --profile robust --pad`` draws 5 % of its frames over bare ground
    (helipad_1m without them found the pad in unseen ground's texture and landed 31.6 m off on
    the validation seed; with them 60 of 60); a run saved before ``pad_away_fraction`` (None)
    keeps the CNN stage's share, and a share out of range is refused by name."""
    from training.profiles import Profile

    robust = PROFILES["robust"]
    assert robust.pad_away_fraction == 0.05 and robust.teach_away_fraction == 0.05
    assert robust.perception_away_fraction == 0.0  # the full pipeline's CNN stage as before
    older = Profile(**{**robust.to_dict(), "pad_away_fraction": None})
    assert older.teach_away_fraction == robust.perception_away_fraction
    assert PROFILES["robust_sites_teach"].teach_away_fraction == 0.05
    with pytest.raises(PipelineError, match=r"pad_away_fraction = 0\.6; expected 0 <= share"):
        Profile(**{**robust.to_dict(), "pad_away_fraction": 0.6})


# --------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def taught(tmp_path_factory) -> Path:
    """One pad run on the tiny budget, from the shipped model."""
    out = tmp_path_factory.mktemp("teach") / "helipad"
    run_pipeline(out, TINY, pad=str(HELIPAD), start_from=str(SHIPPED), progress=False)
    return out


def test_pad_run_retrains_the_cnn_on_frames_with_the_pad(taught):
    stages = sorted(p.stem for p in (taught / "stages").glob("*.json"))
    assert stages == ["eval", "perception", "vision"]  # no collect, bc, dagger
    profile = json.loads((taught / "profile.json").read_text())
    assert profile["pad"]["name"] == "helipad_1m"
    assert profile["pad"]["start_altitude_m"] == pytest.approx([18.75, 25.0])
    assert profile["started_from"]["sha256"] == sha256_file(SHIPPED)
    # the CNN's data: rendered with the helipad, in every world of the profile's
    _, _, _, meta = load_networks(taught / "checkpoints" / "perception.pt")
    assert meta["data"]["pad"]["name"] == "helipad_1m"
    frames = Path(meta["data"]["pose_frames"])
    with np.load(frames) as z:
        key = str(z["key"])
        assert z["images"].shape[0] == TINY.pad_pose_frames
        altitudes = -z["pos"][:, 2]
    assert str(HELIPAD.resolve()) in key and key.count("helipad_1m") >= 4
    assert altitudes.max() <= 110.0 * 0.25 and altitudes.min() >= 0.25  # scaled to the pad
    # the worlds the run flies: the robust profile's, with the pad and the pad's altitudes
    worlds = (taught / "worlds" / "worlds.toml").read_text()
    for name in ("nominal", "earth_mixed", "mars_mixed", "mars"):
        assert f"[worlds.{name}]" in worlds
        text = (taught / "worlds" / f"{name}.toml").read_text()
        assert 'design = ["helipad_1m"]' in text and "altitude_m = [18.75, 25.0]" in text
    # the controller is the shipped one, the CNN is not; the lowest fix scales with the pad
    cfg0, ctrl0, cnn0, _ = load_networks(SHIPPED)
    cfg1, ctrl1, cnn1, _ = load_networks(taught / "checkpoints" / "vision.pt")
    assert cfg1.min_fix_altitude_m == pytest.approx(cfg0.min_fix_altitude_m * 0.25)
    for k, v in ctrl0.state_dict().items():
        assert torch.equal(v, ctrl1.state_dict()[k]), k
    assert any(not torch.equal(v, cnn1.state_dict()[k]) for k, v in cnn0.state_dict().items())
    # the close frames: 0.3-1.5 m scaled with the pad, the pad in view, the shipped CNN's answers
    n_close = round(TINY.pad_close_fraction * TINY.pad_pose_frames)
    with np.load(taught / "cache" / f"poses_s{TINY.seed + 7}_n{n_close}.npz") as z:
        close_alt, close_images = -z["pos"][:, 2], z["images"]
        close_labels = bearing_labels(z["pos"], z["quat"], load_sim().camera.fov_deg)
    assert close_alt.min() >= 0.3 * 0.25 and close_alt.max() <= 1.5 * 0.25
    assert close_labels[:, 2].all() and len(close_images) == n_close == 128


def test_pad_run_evaluates_on_its_suite_and_ships_its_own_card(taught, tmp_path, capsys):
    m = PadMetrics.from_dict(json.loads((taught / "pad_metrics.json").read_text()))
    assert m.eval_seed == EVAL_SEED != m.profile.validation_seed
    for path, policy in ((m.report, taught / "checkpoints" / "vision.pt"), (m.baseline, SHIPPED)):
        report = SuiteReport.load(path)
        assert report.policy == str(policy) and report.seed == EVAL_SEED
        assert list(report.conditions) == [
            "nominal",
            "low_sun",
            "unseen_terrain",
            "wind_moderate_gusts",
        ]
        assert all(r.episodes == 2 for r in report.conditions.values())
    # a rerun resumes: every stage done, nothing flown again
    before = (taught / "suite.json").read_text()
    run_pipeline(taught, TINY, pad=str(HELIPAD), start_from=str(SHIPPED), progress=False)
    assert (taught / "suite.json").read_text() == before

    code, out, err = run(capsys, "ship", "--run", str(taught), "--out", str(tmp_path))
    assert code == 0, err
    model = tmp_path / "visland_vision_helipad_1m.pt"
    card = (tmp_path / "visland_vision_helipad_1m.md").read_text()
    assert model.is_file() and str(model) in out
    assert (tmp_path / "visland_vision_helipad_1m.control.onnx").is_file()
    assert not (tmp_path / "MODEL_CARD.md").exists()  # the shipped model's card is not touched
    assert sha256_file(model) == sha256_file(taught / "checkpoints" / "vision.pt")
    assert "pad `helipad_1m`" in card and "18.75 and 25 m" in card
    assert "--pad configs/pads/helipad_1m.toml --from" in card
    # the profile's estimator settings that differ from the --from model's are named
    assert "`radar_terrain_slope_deg` 12.0 (`visland_vision.pt`: 0.0)" in card
    for name in ("nominal", "low_sun", "unseen_terrain", "wind_moderate_gusts"):
        assert f"| {name} |" in card
    # under a variant's name (a run that taught the paper's pad in other worlds), with a suite
    # flown by the run's model; a report of another model is refused before anything is written
    other = tmp_path / "variant"
    args = ("ship", "--run", str(taught), "--out", str(other), "--name", "sites")
    code, _, err = run(capsys, *args, "--suite-report", m.baseline)
    assert code == 2 and "is not the model being shipped" in err and not other.exists()
    code, out, err = run(capsys, *args, "--suite-report", m.report)
    assert code == 0, err
    model = other / "visland_vision_sites.pt"
    card = (other / "visland_vision_sites.md").read_text()
    assert sha256_file(model) == sha256_file(taught / "checkpoints" / "vision.pt")
    assert sorted(p.name for p in other.glob("*.md")) == ["visland_vision_sites.md"]
    assert f"visland ship --run {taught} --name sites" in card
    assert f"## Results on `{SuiteReport.load(m.report).suite}`" in card


def test_pad_vision_rounds_stop_when_validation_stops_improving(tmp_path, monkeypatch):
    """``pad_vision_patience`` 1: the rounds go on while each beats the best validation score
    before it and stop after the first that does not; every round flown is validated once."""
    import training.stages.teach as teach_stage

    monkeypatch.setattr(teach_stage, "PAD_VALIDATION_SUCCESS", 1.01)  # the rounds always fly
    prof = replace(TINY, vision_rounds=3, vision_rollouts=2, vision_steps=20, pad_vision_patience=1)
    out = tmp_path / "helipad"
    start, stages = str(SHIPPED), ("perception", "vision")
    run_pipeline(out, prof, pad=str(HELIPAD), start_from=start, stages=stages, progress=False)
    rec = json.loads((out / "stages" / "vision.json").read_text())
    names = [Path(v["checkpoint"]).stem for v in rec["validation"]]
    flown = len(names) - 1
    assert names == ["vision_prior", *(f"vision_r{k}" for k in range(flown))]
    assert 1 <= flown <= 3 and len(rec["fits"]) == flown
    scores = [v["score"] for v in rec["validation"]]
    for k in range(flown):
        better = scores[k + 1] < min(scores[: k + 1])
        if k < flown - 1:
            assert better  # an improving round: the next one flies
        elif flown < 3:
            assert not better  # the round that stopped them
    assert not (out / "checkpoints" / f"vision_r{flown}.pt").exists()


# --------------------------------------------------------------------------- bad input


def test_bad_pad_file_exits_2_naming_it(capsys, tmp_path):
    missing = tmp_path / "no_such_pad.toml"
    out = tmp_path / "run"
    argv = ("pipeline", "--profile", "robust", "--from", str(SHIPPED), "--out", str(out))
    code, _, err = run(capsys, *argv, "--pad", str(missing))
    assert code == 2 and str(missing) in err and "not found" in err
    assert not out.exists()  # refused before any folder was made
    bad = tmp_path / "typo.toml"
    bad.write_text('name = "typo"\nsize_m = [1.0, 1.0]\npatern = "helipad"\n')
    code, _, err = run(capsys, *argv, "--pad", str(bad))
    assert code == 2 and str(bad) in err and "patern" in err


def test_pad_needs_a_matching_model_to_start_from(tmp_path):
    with pytest.raises(PipelineError, match="--pad needs --from"):
        run_pipeline(tmp_path / "a", TINY, pad="helipad_1m", progress=False)
    # the quick profile's network has no hover input; the shipped model has
    with pytest.raises(PipelineError, match="hover_input"):
        run_pipeline(tmp_path / "b", PROFILES["quick"], pad="helipad_1m", start_from=str(SHIPPED))
    with pytest.raises(PipelineError, match="expected a checkpoint file"):
        run_pipeline(tmp_path / "c", TINY, pad="helipad_1m", start_from=str(tmp_path))
    with pytest.raises(ConfigError, match="pad file not found"):
        teach_pad(tmp_path / "none.toml")


def test_the_teach_darkens_frames_as_a_low_sun_does_within_checked_bounds():
    from training.profiles import Profile
    from training.train import train_perception

    # a low sun (5-12 deg) leaves about 0.4 of the nominal grey levels; the robust profile's
    # teach draws gains down to 0.3, every other profile keeps the CNN stage's 0.8
    assert PROFILES["robust"].pad_perception_min_gain == 0.3
    assert PROFILES["quick"].pad_perception_min_gain == 0.8
    for bad in (0.0, 1.5):
        with pytest.raises(PipelineError, match=f"pad_perception_min_gain = {bad}"):
            Profile(**{**PROFILES["quick"].to_dict(), "pad_perception_min_gain": bad})
    cnn = load_networks(SHIPPED)[2]
    frames = (np.zeros((4, 128, 128), np.uint8), np.zeros((4, 3)), np.tile([1.0, 0, 0, 0], (4, 1)))
    with pytest.raises(ValueError, match=r"gain = \(1\.3, 1\.2\)"):
        train_perception(cnn, [], 1, extra=frames, gain=(1.3, 1.2))


def test_a_pad_run_is_resumed_only_as_one(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(PipelineError, match="--pad needs --from"):
        run_pipeline(out, TINY, pad="helipad_1m", progress=False)
    with pytest.raises(PipelineError, match="teaches pad 'helipad_1m'"):
        run_pipeline(out, TINY, stages=("perception",), progress=False)
    with pytest.raises(PipelineError, match=r"differs in .*pad"):
        run_pipeline(out, TINY, pad="quadrant_2m", progress=False)
