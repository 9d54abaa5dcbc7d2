"""Physics and sensors on a site's surfaces (issue 32): drops onto a slope, a rock, a heaving
deck and a driving rover behave as physics says; the radar measures along the body's down axis
to whatever lies below; landings are scored in the pad's frame; the privileged expert lands on
every kind of site; the ground-truth channel carries the pad's state, through the log too."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import rocky_site, scenario_with

from companion.contract import Command, GroundTruth
from companion.contract.records import GroundTruthRecord
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.env import LandingEnv
from sitl_sim.metrics import EpisodeResult
from sitl_sim.physics.dynamics import quat_to_rotation
from sitl_sim.scenario import InitialState
from sitl_sim.simulator import Simulator
from sitl_sim.site.contact import TIP_OVER_DEG, quat_from_rotation
from sitl_sim.world import episode_world
from training.exec.rollout import fly_episode, make_policy

MOTORS_OFF = None  # disarmed: rotors commanded to zero


def _sim(scenario, seed=3, index=0, start=(0.0, 0.0, -3.0), vel=(0.0, 0.0, 0.0), euler=(0, 0, 0)):
    sim = Simulator(load_vehicle(), load_sim(), render=False)
    world = episode_world(scenario, seed, index)
    initial = InitialState(start, vel, tuple(euler), (0.0, 0.0, 0.0))
    sim.reset(initial, np.random.SeedSequence([seed, index]), world=world)
    return sim


def _fall(sim, seconds=3.0, command=MOTORS_OFF):
    first = None
    for _ in range(round(seconds * sim.sim.control_rate_hz)):
        event = sim.step(command)
        first = first or event
    return first


def test_a_drop_onto_a_slope_comes_to_rest_square_to_it_where_it_touched():
    sim = _sim(scenario_with(terrain={"slope_deg": 12.0}), start=(1.0, -0.5, -3.0))
    site = sim.site
    event = _fall(sim)
    assert event is not None and event.pad is not None
    # the same fall as onto the flat ground from the same height above it (motors spinning
    # down, drag): contact after the same time, at the same speed
    drop = 3.0 - site.ground_height(1.0, -0.5)
    flat = Simulator(load_vehicle(), load_sim(), render=False)
    flat.reset(InitialState((1.0, -0.5, -drop), (0, 0, 0), (0, 0, 0), (0, 0, 0)), 1)
    same = _fall(flat)
    assert event.time_s == pytest.approx(same.time_s, abs=1e-3)
    assert event.vel_ned_m_s == pytest.approx(same.vel_ned_m_s, abs=1e-2)
    truth = sim.ground_truth()
    n, e, d = truth.pos_ned_m
    assert (n, e) == pytest.approx((1.0, -0.5), abs=1e-6)  # full friction: it stays put
    assert -d == pytest.approx(site.ground_height(n, e), abs=1e-9)
    assert not truth.vel_ned_m_s.any() and not truth.accel_ned_m_s2.any()
    body_down = quat_to_rotation(truth.quat_wxyz)[:, 2]
    assert body_down @ -np.array(site.ground_normal(n, e)) == pytest.approx(1.0, abs=1e-9)
    # the pad lies on the slope: scored in its frame the vehicle came down level, 12 deg off
    result = EpisodeResult.from_contact(event)
    assert result.tilt_deg == pytest.approx(12.0, abs=0.05)
    assert result.touched_pad and not result.tipped_over
    assert result.landing_error_m == pytest.approx(math.hypot(1.0, -0.5), rel=0.03)
    assert sim.on_ground()


def test_a_slope_too_steep_to_stand_on_tips_the_vehicle_over():
    sim = _sim(scenario_with(terrain={"slope_deg": TIP_OVER_DEG + 4.0}), start=(0.0, 0.0, -1.0))
    result = EpisodeResult.from_contact(_fall(sim))
    assert result.tipped_over and not result.success
    gentle = _sim(scenario_with(terrain={"slope_deg": TIP_OVER_DEG - 4.0}), start=(0, 0, -0.2))
    assert not EpisodeResult.from_contact(_fall(gentle)).tipped_over


def test_a_hard_landing_on_a_rock_meets_its_top_and_is_scored_off_the_pad():
    sc, site, _, (n, e) = rocky_site(seed=5, index=1)
    sim = _sim(sc, seed=5, index=1, start=(n, e, -6.0), vel=(0.0, 0.0, 3.0))
    event = _fall(sim)
    top = site.ground_height(n, e)
    assert top > 0.25
    assert -event.pos_ned_m[2] == pytest.approx(top, abs=1e-6)  # on the rock, not the ground
    result = EpisodeResult.from_contact(event)
    assert result.touchdown_vertical_speed_m_s > 5.0 and not result.success  # a hard landing
    assert not result.touched_pad
    assert result.landing_error_m == pytest.approx(math.hypot(n, e), abs=1e-6)
    # resting on the rock: the radar reads nearly nothing, the ground truth is at rest
    assert sim.ground_truth().pos_ned_m[2] == pytest.approx(-top, abs=1e-6)


def test_a_vehicle_on_a_heaving_deck_rides_it_and_its_touchdown_is_relative_to_it():
    deck = {
        "motion": "deck",
        "height_m": 2.0,
        "speed_m_s": 1.0,
        "heading_deg": 40.0,
        "heave_m": 0.5,
        "heave_period_s": 5.0,
        "roll_deg": 5.0,
        "pitch_deg": 5.0,
    }
    sc = scenario_with(pad=deck, visual={"terrain": ["water"]})
    sim = _sim(sc, start=(0.0, 0.0, -3.0))
    site = sim.site
    event = _fall(sim, seconds=1.0)
    assert event is not None
    pad_at = site.pad_pose(event.time_s)
    # relative to the deck: the fall's speed minus the deck's own
    rel_down = pad_at.R_pad_to_ned.T @ (event.vel_ned_m_s - pad_at.velocity_ned)
    result = EpisodeResult.from_contact(event)
    assert result.touchdown_vertical_speed_m_s == pytest.approx(rel_down[2], abs=0.05)
    # the deck drifted on under the falling vehicle: the error is in its frame
    rel = pad_at.R_pad_to_ned.T @ (event.pos_ned_m - pad_at.position_ned)
    assert result.landing_error_m == pytest.approx(math.hypot(rel[0], rel[1]))
    assert result.touched_pad and 0.3 < result.landing_error_m < 0.5  # ~1 m/s for 0.41 s
    # carried: at every later step the vehicle sits at the same point of the deck, square to it
    offsets = []
    for _ in range(40):
        sim.step(MOTORS_OFF)
        truth = sim.ground_truth()
        pose = site.pad_pose(truth.time_s)
        offsets.append(pose.R_pad_to_ned.T @ (truth.pos_ned_m - pose.position_ned))
        assert np.allclose(quat_to_rotation(truth.quat_wxyz)[:, 2], pose.R_pad_to_ned[:, 2])
        assert np.allclose(truth.vel_ned_m_s, pose.velocity_ned, atol=0.1)
        assert truth.pad_pos_ned_m == pytest.approx(pose.position_ned)
    assert np.ptp(np.array(offsets), axis=0).max() < 1e-6
    assert sim.on_ground()
    # full thrust lifts it off the deck again
    for _ in range(5):
        sim.step(Command.from_array([1.0, 0.0, 0.0, 0.0]))
    assert not sim.on_ground()


def test_a_drop_beside_the_rover_lands_on_the_ground_and_not_on_the_pad():
    rover = {"motion": "rover", "height_m": 1.5, "speed_m_s": 2.0, "heading_deg": 0.0}
    sim = _sim(scenario_with(pad=rover), start=(0.0, 8.0, -2.0))  # 8 m to its right
    event = _fall(sim)
    result = EpisodeResult.from_contact(event)
    assert event.pos_ned_m[2] == pytest.approx(0.0, abs=1e-9)  # the ground
    assert not result.touched_pad and not result.success
    onto = _sim(scenario_with(pad=rover), start=(1.0, 0.0, -4.0))  # over the bed
    result = EpisodeResult.from_contact(_fall(onto))
    assert result.touched_pad
    assert -onto.ground_truth().pos_ned_m[2] == pytest.approx(1.5, abs=1e-6)  # on its roof
    # driving on with it, at its speed
    assert onto.ground_truth().vel_ned_m_s[:2] == pytest.approx([2.0, 0.0], abs=1e-3)


def test_the_radar_measures_along_the_body_axis_to_whatever_lies_below():
    sc = scenario_with(terrain={"slope_deg": 6.0, "relief_m": 1.0, "craters_per_km2": 2000.0})
    sim = _sim(sc, seed=7, start=(20.0, -15.0, -30.0), euler=(0.2, -0.1, 0.5))
    truth = sim.ground_truth()
    down = quat_to_rotation(truth.quat_wxyz)[:, 2]
    expected = sim.site.range_along(truth.pos_ned_m, down, truth.time_s, 100.0)
    hit = truth.pos_ned_m + expected * down
    assert sim.site.ground_height(hit[0], hit[1]) == pytest.approx(-hit[2], abs=1e-5)
    assert sim.radar.true_range(truth.pos_ned_m, truth.quat_wxyz, truth.time_s) == expected
    # ...and on the rover, its roof: the range drops by the roof's height
    rover = {"motion": "rover", "height_m": 1.5, "speed_m_s": 2.0, "heading_deg": 0.0}
    over = _sim(scenario_with(pad=rover), start=(0.0, 0.0, -10.0))
    gt = over.ground_truth()
    assert over.radar.true_range(gt.pos_ned_m, gt.quat_wxyz, 0.0) == pytest.approx(8.5)
    # 5 s later the rover has driven 10 m on: the beam meets the ground again
    assert over.radar.true_range(gt.pos_ned_m, gt.quat_wxyz, 5.0) == pytest.approx(10.0)


def test_the_ground_truth_carries_the_pad_state_and_the_log_keeps_it():
    rover = {"motion": "rover", "height_m": 1.5, "speed_m_s": 2.5, "heading_deg": 90.0}
    sim = _sim(scenario_with(pad=rover), start=(0.0, 0.0, -20.0))
    for _ in range(20):
        sim.step(Command.from_array([0.5, 0.0, 0.0, 0.0]))
    truth = sim.ground_truth()
    assert truth.pad_vel_ned_m_s == pytest.approx([0.0, 2.5, 0.0], abs=1e-6)
    assert truth.pad_pos_ned_m == pytest.approx([0.0, 2.5 * truth.time_s, -1.5], abs=1e-6)
    r = quat_to_rotation(truth.pad_quat_wxyz)
    assert r[:, 0] == pytest.approx([0.0, 1.0, 0.0], abs=1e-9)  # it faces east
    rel_pos, rel_vel = truth.pad_relative
    assert rel_pos == pytest.approx(truth.pos_ned_m - truth.pad_pos_ned_m)
    assert rel_vel == pytest.approx(truth.vel_ned_m_s - truth.pad_vel_ned_m_s)
    record = GroundTruthRecord.from_groundtruth(truth, 7)
    back = GroundTruthRecord.from_dict(record.to_dict()).groundtruth(truth.time_s)
    for name in ("pad_pos_ned_m", "pad_vel_ned_m_s", "pad_quat_wxyz", "pad_accel_ned_m_s2"):
        assert getattr(back, name) == pytest.approx(getattr(truth, name))
    # the nominal world carries none, and its record is the one it always was
    nominal = Simulator(load_vehicle(), load_sim(), render=False)
    nominal.reset(InitialState((0, 0, -5), (0, 0, 0), (0, 0, 0), (0, 0, 0)), 1)
    gt = nominal.ground_truth()
    assert gt.pad_pos_ned_m is None
    assert "pad_pos_ned_m" not in GroundTruthRecord.from_groundtruth(gt, 0).to_dict()
    with pytest.raises(ValueError, match="all four or none"):
        GroundTruth(
            0.0,
            np.zeros(3),
            np.zeros(3),
            np.array([1.0, 0, 0, 0]),
            np.zeros(3),
            pad_pos_ned_m=np.zeros(3),
        )


def test_rotation_to_quaternion_round_trips():
    rng = np.random.default_rng(0)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= np.sign(q[0])
        assert quat_from_rotation(quat_to_rotation(q)) == pytest.approx(q, abs=1e-9)


@pytest.mark.parametrize("site", ["rover_fast", "deck_moderate", "slope", "rocks", "mars_craters"])
def test_the_expert_lands_on_every_kind_of_site_in_the_pads_frame(site):
    env = LandingEnv(scenario=f"configs/sites/{site}.toml", render_camera=False)
    try:
        expert = make_policy("expert", env)
        for index in range(2):
            out = fly_episode(env, expert, 500, index)
            r = out.result
            assert r.success and r.touched_pad and not r.tipped_over, r
            assert r.landing_error_m < 0.1 and r.touchdown_speed_m_s <= 0.5
    finally:
        env.close()


def test_card_the_expert_lands_on_a_turning_rover_over_mavlink_and_the_log_shows_it(tmp_path):
    """The SITL sends the pad's state as ODOMETRY from PAD_ODOMETRY_COMPONENT with
    --groundtruth; the companion hands it to the privileged expert, which lands on the rover's
    roof; ``visland log plot`` draws the path in the pad's frame beside the world's."""
    from companion.flightlog import read_log
    from tools.log_plots import plot_flight
    from training.exec.fly import FlyConfig, fly

    report = fly(
        FlyConfig(
            policy="expert",
            scenario="configs/sites/rover_fast.toml",
            episodes=1,
            seed=500,
            out=str(tmp_path / "run"),
            progress=False,
            companion_args=("--max-age-ms", "3000"),
            sitl_args=("--lockstep-timeout-s", "5"),
        )
    )
    (row,) = report.per_episode
    assert row.success and row.touched_pad and row.landing_error_m < 0.1, row
    flight = read_log(row.log)
    pad = [m for m in flight.topic("/groundtruth/state") if "pad_pos_ned_m" in m]
    assert pad and np.linalg.norm(pad[-1]["pad_pos_ned_m"][:2]) > 20.0  # it drove off
    plotted = plot_flight(row.log, tmp_path / "rover.png")
    assert "pad frame" in plotted.drawn and (tmp_path / "rover.png").stat().st_size > 10_000
    # the companion's log replays to the same commands: the pad's stream is told apart in it
    from companion.record import replay_log
    from companion.runtime import PolicyRuntime
    from training.companion_process import resolve_policy

    (companion_log,) = (tmp_path / "run" / "companion").glob("*.mcap")
    replay = replay_log(companion_log, PolicyRuntime(resolve_policy("expert"), "expert"))
    assert replay.errors == [] and replay.commands > 100 and replay.max_abs_diff <= 1e-5


def test_the_companion_joins_the_pads_odometry_to_the_vehicles():
    """Two ODOMETRY streams of one system: the vehicle's from the autopilot, the pad's from
    PAD_ODOMETRY_COMPONENT; the ground truth at a time carries both, the pad's acceleration from
    its last two samples."""
    from pymavlink.dialects.v20 import common as mavlink

    from companion.contract import PAD_ODOMETRY_COMPONENT
    from companion.telemetry import TelemetryStore

    store = TelemetryStore()
    enc = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    pad_enc = mavlink.MAVLink(None, srcSystem=1, srcComponent=PAD_ODOMETRY_COMPONENT)
    nan21 = [math.nan] + [0.0] * 20

    def odometry(encoder, t_s, pos, vel):
        msg = encoder.odometry_encode(
            round(t_s * 1e6), 1, 1, *pos, [1.0, 0, 0, 0], *vel, 0, 0, 0, nan21, nan21, 0, 0, 100
        )
        return mavlink.MAVLink(None).decode(bytearray(msg.pack(encoder)))

    for k, t in enumerate((1.0, 1.02, 1.04)):
        assert store.update(odometry(enc, t, (5.0, 0.0, -20.0), (0, 0, 1.0)), t)
        vel = (2.0 + 0.5 * k * 0.02, 0.0, 0.0)  # accelerating at 0.5 m/s^2
        assert store.update(odometry(pad_enc, t, (2.0 * t, 0.0, -1.5), vel), t)
    gt = store.groundtruth_at(1.04)
    assert gt.pos_ned_m == pytest.approx([5.0, 0.0, -20.0])
    assert gt.pad_pos_ned_m == pytest.approx([2.08, 0.0, -1.5])
    assert gt.pad_accel_ned_m_s2 == pytest.approx([0.5, 0.0, 0.0], abs=1e-6)
    assert gt.pad_relative[0] == pytest.approx([2.92, 0.0, -18.5])
    # no pad stream (the nominal site): the vehicle's ODOMETRY alone, as always
    plain = TelemetryStore()
    plain.update(odometry(enc, 1.0, (5.0, 0.0, -20.0), (0, 0, 1.0)), 1.0)
    assert plain.groundtruth_at(1.0).pad_pos_ned_m is None


def test_the_camera_of_a_vehicle_come_down_beside_the_rover_still_gives_frames():
    """Its camera lies in the ground's plane: the fast renderer's ground homography is singular
    there, and a frame (not an exception) must come out, as on the nominal site."""
    rover = {"motion": "rover", "height_m": 1.5, "speed_m_s": 2.0, "heading_deg": 0.0}
    sim = Simulator(load_vehicle(), load_sim())
    try:
        world = episode_world(scenario_with(pad=rover, visual={"terrain": ["asphalt"]}), 1, 0)
        sim.reset(InitialState((0.0, 8.0, -2.0), (0, 0, 0), (0, 0, 0), (0, 0, 0)), 1, world=world)
        _fall(sim, seconds=2.0)
        assert sim.ground_truth().pos_ned_m[2] == pytest.approx(0.0, abs=1e-9)
        image = sim.observe().image
        assert image.shape == (128, 128) and image.any()
    finally:
        sim.close()


def test_the_site_ablation_shows_the_expert_needs_the_pads_motion():
    """``python -m tools.site_ablation``: the expert given the pad's whole state lands on a
    fast rover; given only where it is, or nothing, it does not."""
    from tools.site_ablation import ablate

    rows = {r["variant"]: r for r in ablate(["rover_fast"], episodes=2)}
    assert rows["full"]["success"] == 2 and rows["full"]["error_max_m"] < 0.1
    assert rows["position_only"]["success"] == 0 and rows["still_pad"]["on_pad"] == 0
