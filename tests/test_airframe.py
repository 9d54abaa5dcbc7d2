"""The ``[vehicle]`` scenario section (airframe randomisation) and T_max per planet: config
errors, determinism, the physics of a scaled airframe, MPC_THR_HOVER over MAVLink, the expert
flying and relabelling the episode's vehicle, and nominal flights unchanged bit for bit."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from flights import sitl_with_client
from helpers import edited_config
from pymavlink.dialects.v20 import common as mavlink

from companion.contract import Command
from companion.contract.topics import TOPIC_COMMAND, TOPIC_LABEL, TOPIC_SCENARIO
from companion.flightlog import read_log
from expert.cascade import CascadeLander
from expert.mpc import MpcExpert
from expert.relabel import RelabelError, relabel_log
from sitl_sim.config import CONFIG_DIR, PLANETS, load_vehicle
from sitl_sim.env import LandingEnv
from sitl_sim.errors import ConfigError
from sitl_sim.physics.airframe import (
    AIRFRAME_KEYS,
    AirframeConfig,
    AirframeScales,
    draw_airframe,
)
from sitl_sim.scenario import InitialState, InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator
from sitl_sim.world import EpisodeWorld, episode_world
from tools.sitl_client import ClientTimeout
from training.exec.rollout import episode_pilot, fly_episode, make_policy

EARTH, MARS = PLANETS["earth"], PLANETS["mars"]
HEAVY = CONFIG_DIR / "scenario_heavy.toml"
LIGHT = CONFIG_DIR / "scenario_light.toml"


def _scenario(tmp_path: Path, base: str, section: str, name: str = "s.toml") -> Path:
    path = tmp_path / name
    path.write_text(base + "\n[vehicle]\n" + section + "\n")
    return path


@pytest.fixture(scope="module")
def nominal_text() -> str:
    return (CONFIG_DIR / "scenario.toml").read_text()


# --------------------------------------------------------------------------- nominal unchanged

# sha256 (first 16 hex digits) of every step's command, ground truth, specific force and range
# of a 40-step flight (seed 123, episode 2, no camera), recorded at b19caf6 — before T_max was
# stated per planet and before [vehicle] existed. Regenerate only for a deliberate physics change.
_NOMINAL_DIGESTS = {
    ("scenario.toml", "mpc"): "cc1316387b63deb3",
    ("scenario_mars.toml", "mpc"): "1d135a691be74782",
    ("scenario_wind.toml", "mpc"): "a5bc5ae5a5585e31",
    ("scenario.toml", "cascade"): "e1d1ae23bfa853fd",
}


def _flight_digest(scenario: str | Path, pilot: str, steps: int = 40) -> str:
    env = LandingEnv(scenario=scenario, render_camera=False)
    try:
        policy = (
            MpcExpert(env.vehicle, env.sim_config)
            if pilot == "mpc"
            else CascadeLander(env.vehicle, env.sim_config.planet)
        )
        env.reset(seed=123, options={"episode_index": 2})
        sim = env.simulator
        state = policy.initial_state()
        truth = sim.ground_truth()
        obs = sim.observe(0, truth)
        h = hashlib.sha256()
        for k in range(steps):
            cmd, state = policy.act(obs, truth, state)
            sim.step(cmd)
            truth = sim.ground_truth()
            obs = sim.observe(k + 1, truth)
            for v in (
                cmd.thrust_norm,
                *cmd.rate_frd_rad_s,
                *truth.pos_ned_m,
                *truth.vel_ned_m_s,
                *truth.quat_wxyz,
                *truth.rate_frd_rad_s,
                *truth.rotor_thrust_n,
                *obs.accel_frd_m_s2,
                obs.range_m,
            ):
                h.update(float(v).hex().encode())
        return h.hexdigest()[:16]
    finally:
        env.close()


@pytest.mark.parametrize(("scenario", "pilot"), sorted(_NOMINAL_DIGESTS))
def test_nominal_flights_are_bit_identical_to_before_airframes(scenario, pilot):
    assert _flight_digest(CONFIG_DIR / scenario, pilot) == _NOMINAL_DIGESTS[(scenario, pilot)]


def test_a_scenario_without_vehicle_flies_the_vehicle_file_itself(vehicle, sim_cfg):
    scenario = load_scenario()
    assert scenario.vehicle is None and "vehicle" not in scenario.to_dict()
    world = episode_world(scenario, 0, 0)
    assert world.airframe is None and world.vehicle(vehicle) is vehicle
    sim = Simulator(vehicle, sim_cfg, render=False)
    phys = sim.phys
    sim.reset(InitialStateSampler(scenario, 0).sample(0), 0, world)
    assert sim.episode_vehicle is vehicle and sim.phys is phys  # nothing rebuilt


# --------------------------------------------------------------------------- config errors


@pytest.mark.parametrize(
    ("section", "match"),
    [
        (
            "mass_scal = [1.0, 1.2]",
            r"s\.toml: \[vehicle\] unknown key\(s\) \['mass_scal'\]; "
            r"expected \['mass_scale', 'inertia_scale'",
        ),
        (
            "mass_scale = [1.3, 1.2]",
            r"s\.toml: \[vehicle\] mass_scale = \[1\.3, 1\.2\]; expected "
            r"factors \[lo, hi\] with 0 < lo <= hi <= 10",
        ),
        ("drag_scale = [0.0, 1.2]", r"s\.toml: \[vehicle\] drag_scale = \[0\.0, 1\.2\]; expected"),
        ("thrust_scale = [-1.0, 1.0]", r"s\.toml: \[vehicle\] thrust_scale = \[-1\.0, 1\.0\]"),
        ("inertia_scale = [1.0, 13.0]", r"s\.toml: \[vehicle\] inertia_scale = .*<= 10"),
        ("mass_scale = [1.2]", r"s\.toml: \[vehicle\] mass_scale = \[1\.2\]; expected \[lo, hi\]"),
        ('motor_time_constant_scale = ["a", 1]', r"\[vehicle\] motor_time_constant_scale = "),
        ("mass_scale = [nan, 1.0]", r"s\.toml: \[vehicle\] mass_scale = \[nan, 1\.0\]"),
    ],
)
def test_bad_vehicle_sections_name_file_key_expected_and_got(
    tmp_path, nominal_text, section, match
):
    with pytest.raises(ConfigError, match=match):
        load_scenario(_scenario(tmp_path, nominal_text, section))


def test_an_airframe_that_cannot_hover_is_refused_naming_the_keys(tmp_path, nominal_text):
    path = _scenario(tmp_path, nominal_text, "mass_scale = [1.0, 2.0]\nthrust_scale = [0.7, 1.0]")
    with pytest.raises(
        ConfigError,
        match=r"s\.toml: \[vehicle\] mass_scale up to 2\.0 with "
        r"thrust_scale down to 0\.7 needs 1\.12 x T_max to hover on earth",
    ):
        LandingEnv(scenario=path, render_camera=False)


def test_flying_a_planet_without_its_t_max_names_the_file_and_planet(tmp_path):
    path = edited_config(tmp_path, "vehicle.toml", "mars = 25.0", "")
    vehicle = load_vehicle(path)
    assert vehicle.max_total_thrust_n(EARTH) == 25.0
    with pytest.raises(
        ConfigError,
        match=rf"{path}: \[vehicle\.max_total_thrust_n\] has no "
        r"T_max for planet 'mars' \(stated: \['earth'\]\)",
    ):
        LandingEnv(vehicle=path, scenario=CONFIG_DIR / "scenario_mars.toml", render_camera=False)


# --------------------------------------------------------------------------- determinism


def test_factors_are_a_pure_function_of_seed_and_episode_and_absent_keys_are_one():
    cfg = AirframeConfig(mass_scale=(0.7, 1.3), drag_scale=(0.5, 2.0))
    a, b = draw_airframe(cfg, 5, 3), draw_airframe(cfg, 5, 3)
    assert a == b
    assert draw_airframe(cfg, 5, 4) != a and draw_airframe(cfg, 6, 3) != a
    assert 0.7 <= a.mass_scale <= 1.3 and 0.5 <= a.drag_scale <= 2.0
    assert a.inertia_scale == a.thrust_scale == a.motor_time_constant_scale == 1.0
    # adding a key leaves the other keys' factors where they were
    more = draw_airframe(replace(cfg, thrust_scale=(0.9, 1.1)), 5, 3)
    assert (more.mass_scale, more.drag_scale) == (a.mass_scale, a.drag_scale)
    assert more.thrust_scale != 1.0
    # uniform: 2000 episodes fill the range evenly (mean within 4 sigma of the midpoint)
    draws = [draw_airframe(cfg, 9, i).mass_scale for i in range(2000)]
    assert min(draws) >= 0.7 and max(draws) <= 1.3
    assert abs(np.mean(draws) - 1.0) < 4 * 0.6 / math.sqrt(12 * 2000)


def test_adding_vehicle_changes_neither_the_wind_nor_the_initial_states(tmp_path):
    windy = (CONFIG_DIR / "scenario_wind.toml").read_text()
    plain = load_scenario(CONFIG_DIR / "scenario_wind.toml")
    scaled = load_scenario(_scenario(tmp_path, windy, "mass_scale = [0.7, 1.3]"))
    for i in range(5):
        assert InitialStateSampler(plain, 8).sample(i) == InitialStateSampler(scaled, 8).sample(i)
        a, b = episode_world(plain, 8, i), episode_world(scaled, 8, i)
        assert a.airframe is None and b.airframe is not None
        assert (a.wind.speed_m_s, a.wind.direction_deg) == (b.wind.speed_m_s, b.wind.direction_deg)
        a.wind.start((0.0, 0.0, -50.0))
        b.wind.start((0.0, 0.0, -50.0))
        np.testing.assert_array_equal(a.wind.wind_ned_m_s, b.wind.wind_ned_m_s)


def _env_flight(scenario: Path, episode: int, steps: int = 30) -> tuple[list, dict]:
    env = LandingEnv(scenario=scenario, render_camera=False)
    try:
        _, info = env.reset(seed=4, options={"episode_index": episode})
        hover = env.episode_vehicle.hover_thrust_norm(env.sim_config.planet)
        out = []
        for _ in range(steps):
            _, _, _, _, info = env.step(np.array([hover, 0.2, -0.1, 0.05]))
            out.append(info["groundtruth"])
        return out, info
    finally:
        env.close()


def test_same_seed_and_episode_fly_the_same_airframe_bit_for_bit_and_another_episode_another():
    a, info_a = _env_flight(HEAVY, 1)
    b, info_b = _env_flight(HEAVY, 1)
    c, info_c = _env_flight(HEAVY, 2)
    assert (
        info_a["airframe"]
        == info_b["airframe"]
        == draw_airframe(load_scenario(HEAVY).vehicle, 4, 1).to_dict()
    )
    assert info_c["airframe"]["mass_scale"] != info_a["airframe"]["mass_scale"]
    for ga, gb in zip(a, b, strict=True):
        for key in ("pos_ned_m", "vel_ned_m_s", "quat_wxyz", "rate_frd_rad_s"):
            np.testing.assert_array_equal(ga[key], gb[key])
    assert not np.array_equal(a[-1]["pos_ned_m"], c[-1]["pos_ned_m"])
    nominal, info_n = _env_flight(CONFIG_DIR / "scenario.toml", 1)
    assert "airframe" not in info_n
    # the same start and commands, another airframe: another flight
    assert not np.array_equal(nominal[-1]["pos_ned_m"], a[-1]["pos_ned_m"])


# --------------------------------------------------------------------------- physics


def test_scales_apply_to_the_vehicle_file(vehicle):
    scales = AirframeScales(1.3, 1.5, 0.8, 2.0, 0.5)
    v = scales.apply(vehicle)
    assert v.mass_kg == pytest.approx(1.3)
    assert v.inertia_diag_kg_m2 == pytest.approx((0.0135, 0.0135, 0.024))
    assert v.max_total_thrust_n(EARTH) == pytest.approx(20.0)
    assert v.max_total_thrust_n(MARS) == pytest.approx(20.0)
    assert v.motor_time_constant_s == pytest.approx(0.04)
    assert v.drag_coefficient_area_m2 == pytest.approx((0.01, 0.01, 0.02))
    assert v.rate_controller == vehicle.rate_controller and v.arm_length_m == vehicle.arm_length_m
    # MPC_THR_HOVER of the episode: m g / (T_max thrust_scale)
    assert v.hover_thrust_norm(EARTH) == pytest.approx(1.3 * 9.81 / (25.0 * 0.8), rel=1e-12)
    assert v.hover_thrust_norm(MARS) == pytest.approx(1.3 * 3.71 / (25.0 * 0.8), rel=1e-12)
    assert AirframeScales().apply(vehicle) == vehicle
    assert set(scales.to_dict()) == set(AIRFRAME_KEYS)
    assert AirframeScales.from_dict(scales.to_dict(), "x") == scales


def test_a_heavier_vehicle_at_the_nominal_hover_thrust_sinks_at_g_times_the_missing_lift(
    vehicle, quiet_cfg
):
    """1.3 x the mass at the vehicle file's hover thrust: a = g (1 - 1/1.3) = 2.26 m/s^2 down;
    at its own hover thrust it holds its altitude."""
    sim = Simulator(vehicle, quiet_cfg, render=False)
    start = InitialState((0.0, 0.0, -50.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    heavy = EpisodeWorld(airframe=AirframeScales(mass_scale=1.3))
    sim.reset(start, 0, heavy)
    assert sim.episode_vehicle.mass_kg == pytest.approx(1.3) and sim.phys.mass == pytest.approx(1.3)
    nominal_hover = Command(vehicle.hover_thrust_norm(EARTH), np.zeros(3))
    for _ in range(3):  # 0.3 s: 15 rotor time constants; drag at 0.7 m/s is < 0.01 m/s^2
        sim.step(nominal_hover)
    accel_down = sim.ground_truth().accel_ned_m_s2[2]
    assert accel_down == pytest.approx(9.81 * (1.0 - 1.0 / 1.3), abs=0.015)
    sim.reset(start, 0, heavy)
    own_hover = Command(sim.episode_vehicle.hover_thrust_norm(EARTH), np.zeros(3))
    for _ in range(20):
        sim.step(own_hover)
    assert abs(sim.ground_truth().pos_ned_m[2] + 50.0) < 1e-6
    sim.reset(start, 0)  # back to the vehicle file
    assert sim.episode_vehicle is vehicle and sim.phys.mass == 1.0


# --------------------------------------------------------------------------- MAVLink SITL


def test_sitl_reports_the_episode_hover_thrust_and_announces_a_change(
    tmp_path, low_scenario, loopback_sitl
):
    """Over real UDP: MPC_THR_HOVER read at episode 0 is that airframe's m g / T_max; when
    episode 0 has landed (AUTO.LAND, flown for the heavy airframe), episode 1's value arrives as
    an unrequested PARAM_VALUE; the logs record the factors."""
    scenario = _scenario(
        tmp_path,
        Path(low_scenario).read_text(),
        "mass_scale = [1.1, 1.3]\nthrust_scale = [0.9, 1.0]",
    )
    p, cfg = loopback_sitl(scenario, tmp_path / "logs", seed=3, episodes=2)
    airframe = load_scenario(scenario).vehicle
    expected = [
        draw_airframe(airframe, 3, i).apply(load_vehicle()).hover_thrust_norm(EARTH) for i in (0, 1)
    ]
    assert expected[0] != expected[1]
    with sitl_with_client(p, cfg) as (client, runner):
        try:
            client.wait_for("HEARTBEAT", 5.0)
            client.send(client.mav.param_request_read_encode(1, 1, b"MPC_THR_HOVER", -1))
            msg = client.wait_for("PARAM_VALUE", 3.0, lambda m: m.param_id == "MPC_THR_HOVER")
            assert msg.param_value == pytest.approx(expected[0], rel=1e-6)  # float32 on the wire
            client.inbox.clear()
            accepted = mavlink.MAV_RESULT_ACCEPTED
            assert client.command_long(mavlink.MAV_CMD_NAV_LAND) == accepted  # AUTO.LAND
            pushed = client.wait_for(
                "PARAM_VALUE", 30.0, lambda m: m.param_id == "MPC_THR_HOVER", fresh=False
            )
            assert pushed.param_value == pytest.approx(expected[1], rel=1e-6)
            assert pushed.param_count == 17 and pushed.param_index == 3
        except ClientTimeout as exc:
            raise AssertionError(f"no answer from the SITL: {exc}") from None
    sitl = runner.sitl
    assert sitl.results[0].landed and sitl.results[0].touchdown_vertical_speed_m_s <= 1.0
    for i in (0, 1):
        log = read_log(tmp_path / "logs" / f"sitl_seed3_ep{i:04d}.mcap", topics=[TOPIC_SCENARIO])
        (record,) = log.topic(TOPIC_SCENARIO)
        assert record["airframe"] == draw_airframe(airframe, 3, i).to_dict()
        assert log.metadata["episode"]["airframe"] == record["airframe"]
        assert log.metadata["config"]["params"]["mpc_thr_hover"] == expected[i]
        unscaled = json.loads(json.dumps(load_vehicle().to_dict()))  # the file, as logged
        assert log.metadata["config"]["vehicle"] == unscaled


# --------------------------------------------------------------------------- the expert


@pytest.mark.parametrize("scenario", [HEAVY, LIGHT], ids=["heavy", "light"])
def test_expert_lands_a_heavy_and_a_light_episode_flying_their_airframe(scenario):
    env = LandingEnv(scenario=scenario, render_camera=False)
    try:
        policy = make_policy("expert", env)
        out = fly_episode(env, policy, seed=1_000_000, index=0)
        pilot = episode_pilot(policy, env.episode_vehicle)
        assert pilot is not policy and pilot.vehicle == env.episode_vehicle
        assert episode_pilot(policy, env.episode_vehicle) is pilot  # built once per vehicle
        assert episode_pilot(policy, env.vehicle) is policy  # the nominal path builds nothing
    finally:
        env.close()
    assert out.result.success and out.result.landing_error_m < 0.05
    assert out.policy_stats["solves"] == out.steps and out.policy_stats["failed"] == 0


def test_relabel_labels_a_heavy_flight_with_its_airframe(tmp_path, low_scenario):
    """The expert's own flight of a heavy episode, relabelled offline, gives back its commands:
    the relabeller read the factors from the log (a vehicle-file expert would ask ~20 % less
    thrust). A log from before T_max per planet (one figure) is still accepted when it matches."""
    scenario = _scenario(tmp_path, Path(low_scenario).read_text(), "mass_scale = [1.25, 1.3]")
    env = LandingEnv(scenario=scenario, render_camera=False)
    log_path = tmp_path / "flights" / "ep.mcap"
    log_path.parent.mkdir()
    try:
        policy = make_policy("expert", env)
        fly_episode(env, policy, 0, 0, log_path, source="expert")
        old_vehicle = {
            k: v for k, v in env.vehicle.to_dict().items() if k != "max_total_thrust_n_by_planet"
        }
        config = {
            "vehicle": {**old_vehicle, "max_total_thrust_n": 25.0},
            "sim": env.sim_config.to_dict(),
            "scenario": env.scenario.to_dict(),
        }
        old_log = tmp_path / "flights" / "old.mcap"
        fly_episode(env, policy, 0, 0, old_log, source="expert", metadata={"config": config})
        config["vehicle"]["max_total_thrust_n"] = 20.0
        other_log = tmp_path / "flights" / "other.mcap"
        fly_episode(env, policy, 0, 0, other_log, source="expert", metadata={"config": config})
    finally:
        env.close()
    report = relabel_log(log_path, tmp_path / "labels")
    labels = read_log(Path(report.labels)).topic(TOPIC_LABEL)
    recorded = {m["frame_id"]: m for m in read_log(log_path).topic(TOPIC_COMMAND)}
    assert report.steps == len(recorded) > 20
    for label in labels:  # (labels hold the heading found at each step: yaw rates differ)
        rec = recorded[label["frame_id"]]
        assert label["thrust_norm"] == pytest.approx(rec["thrust_norm"], abs=2e-3)
        roll_pitch = label["rate_frd_rad_s"][:2]
        np.testing.assert_allclose(roll_pitch, rec["rate_frd_rad_s"][:2], atol=1e-3)
    assert relabel_log(old_log, tmp_path / "labels").steps == report.steps
    with pytest.raises(
        RelabelError,
        match=r"flown with another vehicle config \(differs in "
        r"\['max_total_thrust_n_by_planet'\]\)",
    ):
        relabel_log(other_log, tmp_path / "labels")
