"""Sensor faults (``[sensors]``): config checks, determinism, a nominal flight that is exactly
what it was before the section existed, and each fault doing what it says — in process and
over real MAVLink UDP."""

from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path

import numpy as np
import pytest
from flights import fly_cascade, sitl_with_client
from helpers import config_plus

from companion.contract import Command
from companion.flightlog import read_log
from sitl_sim.config import CONFIG_DIR
from sitl_sim.env import LandingEnv
from sitl_sim.errors import ConfigError
from sitl_sim.physics.sensor_faults import SensorFaults, SensorFaultsConfig
from sitl_sim.physics.wind import WindModel
from sitl_sim.render.scene import Camera
from sitl_sim.scenario import InitialState, InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator
from sitl_sim.world import episode_world

SENSORS = """
[sensors]
camera_latency_ms = [50.0, 150.0]
frame_drop_prob = 0.1
radar_dropout_prob = 0.05
radar_outlier_prob = 0.01
radar_outlier_m = [1.0, 150.0]
accel_bias_m_s2 = [0.02, 0.1]
gyro_bias_rad_s = [0.001, 0.005]
"""

NOMINAL_DIGEST = "254e46b21f42aa45e3a66ede98057358c399b93f815e6fe4d4ff3fcebffe4eed"
"""sha256 of :func:`_observation_digest` on configs/scenario.toml, recorded at b19caf6, before
``[sensors]`` existed: the nominal observation sequence must never change."""


def _sensors(tmp_path: Path, extra: str, base: Path = CONFIG_DIR / "scenario.toml"):
    return load_scenario(config_plus(tmp_path, extra, base))


# --------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    "old,new,match",
    [
        (
            "frame_drop_prob = 0.1",
            "frame_drop_prb = 0.1",
            r"scenario\.toml: \[sensors\] unknown key\(s\) \['frame_drop_prb'\]; expected "
            r"\['camera_latency_ms', 'frame_drop_prob',",
        ),
        (
            "frame_drop_prob = 0.1",
            "frame_drop_prob = 1.5",
            r"scenario\.toml: \[sensors\] frame_drop_prob = 1\.5; expected a probability in "
            r"\[0, 1\]",
        ),
        (
            "radar_dropout_prob = 0.05",
            "radar_dropout_prob = nan",
            r"scenario\.toml: \[sensors\] radar_dropout_prob = nan; expected a probability",
        ),
        (
            "radar_dropout_prob = 0.05",
            'radar_dropout_prob = "5%"',
            r"scenario\.toml: \[sensors\] radar_dropout_prob = '5%'; expected a probability",
        ),
        (
            "camera_latency_ms = [50.0, 150.0]",
            "camera_latency_ms = [150.0, 50.0]",
            r"scenario\.toml: \[sensors\] camera_latency_ms = \[150\.0, 50\.0\]; expected finite "
            r"\[lo, hi\] with 0 <= lo <= hi",
        ),
        (
            "camera_latency_ms = [50.0, 150.0]",
            "camera_latency_ms = [-10.0, 150.0]",
            r"\[sensors\] camera_latency_ms = \[-10\.0, 150\.0\]; expected finite \[lo, hi\] "
            r"with 0 <= lo",
        ),
        (
            "camera_latency_ms = [50.0, 150.0]",
            "camera_latency_ms = [50.0, 1500.0]",
            r"scenario\.toml: \[sensors\] camera_latency_ms = \[50\.0, 1500\.0\]; expected finite "
            r"\[lo, hi\] with 0 <= lo <= hi <= 1000 \(ms\)",
        ),
        (
            "accel_bias_m_s2 = [0.02, 0.1]",
            "accel_bias_m_s2 = [0.02, inf]",
            r"scenario\.toml: \[sensors\] accel_bias_m_s2 = \[0\.02, inf\]; expected finite",
        ),
        (
            "gyro_bias_rad_s = [0.001, 0.005]",
            "gyro_bias_rad_s = [0.001, 0.005, 0.01]",
            r"scenario\.toml: \[sensors\] gyro_bias_rad_s = \[0\.001, 0\.005, 0\.01\]; expected "
            r"\[lo, hi\]",
        ),
        (
            "radar_outlier_m = [1.0, 150.0]\n",
            "",
            r"scenario\.toml: \[sensors\] radar_outlier_prob = 0\.01 needs radar_outlier_m",
        ),
        (
            "radar_outlier_prob = 0.01\n",
            "",
            r"scenario\.toml: \[sensors\] radar_outlier_m is set but radar_outlier_prob is 0",
        ),
    ],
)
def test_bad_sensors_sections_name_file_key_expected_and_got(tmp_path, old, new, match):
    assert old in SENSORS
    with pytest.raises(ConfigError, match=match):
        _sensors(tmp_path, SENSORS.replace(old, new))


def test_sensors_section_is_typed_and_nominal_scenarios_are_unchanged():
    sc = load_scenario(CONFIG_DIR / "scenario_sensors.toml")
    assert sc.sensors == SensorFaultsConfig(
        camera_latency_ms=(50.0, 150.0),
        frame_drop_prob=0.1,
        radar_dropout_prob=0.05,
        radar_outlier_prob=0.01,
        radar_outlier_m=(1.0, 150.0),
        accel_bias_m_s2=(0.02, 0.1),
        gyro_bias_rad_s=(0.001, 0.005),
    )
    assert sc.to_dict()["sensors"]["camera_latency_ms"] == [50.0, 150.0]
    nominal = load_scenario()
    assert nominal.sensors is None and "sensors" not in nominal.to_dict()  # logs unchanged
    assert InitialStateSampler(sc, 4).sample(3) == InitialStateSampler(nominal, 4).sample(3)


# --------------------------------------------------------------------------- determinism


def _observation_digest(scenario=None) -> str:
    """40 control steps of episode 3 of seed 7 under a fixed command, no rendering: every
    observation field, then the final sensor times and position."""
    env = LandingEnv(scenario=scenario, render_camera=False)
    hover = env.vehicle.hover_thrust_norm(env.sim_config.planet)
    obs, _ = env.reset(seed=7, options={"episode_index": 3})
    h = hashlib.sha256()
    for _ in range(40):
        for key in sorted(obs):
            h.update(np.ascontiguousarray(obs[key]).tobytes())
        obs, *_ = env.step(np.array([hover, 0.05, -0.03, 0.1]))
    o = env.simulator.observe(frame_id=99)
    for k in ("image_time_s", "range_m", "range_time_s", "imu_time_s", "attitude_time_s"):
        h.update(np.float64(getattr(o, k)).tobytes())
    h.update(np.asarray(env.simulator.ground_truth().pos_ned_m).tobytes())
    env.close()
    return h.hexdigest()


def test_nominal_observations_are_those_recorded_before_sensor_faults(tmp_path):
    assert _observation_digest() == NOMINAL_DIGEST
    # an empty [sensors] turns every fault off: the same flight, bit for bit
    assert _observation_digest(_sensors(tmp_path, "\n[sensors]\n")) == NOMINAL_DIGEST


def _run(scenario, steps: int = 60, seed: int = 7, index: int = 3) -> list:
    env = LandingEnv(scenario=scenario, render_camera=False)
    hover = env.vehicle.hover_thrust_norm(env.sim_config.planet)
    env.reset(seed=seed, options={"episode_index": index})
    sim = env.simulator
    out = [sim.observe(0)]
    for k in range(1, steps):
        env.step(np.array([hover, 0.05, -0.03, 0.1]))
        out.append(sim.observe(k))
    env.close()
    return out


def _fields(o) -> tuple:
    return (
        o.image_time_s,
        o.range_m,
        tuple(o.accel_frd_m_s2),
        tuple(o.attitude_rad),
        tuple(o.rate_frd_rad_s),
    )


def test_same_seed_and_episode_give_the_same_faults_and_observations(tmp_path):
    sc = load_scenario(CONFIG_DIR / "scenario_sensors.toml")
    a, b = (SensorFaults.for_episode(sc.sensors, 5, 2) for _ in range(2))
    c = SensorFaults.for_episode(sc.sensors, 5, 3)
    assert a.camera_latency_s == b.camera_latency_s != c.camera_latency_s
    assert 0.05 <= a.camera_latency_s <= 0.15
    np.testing.assert_array_equal(a.accel_bias_frd_m_s2, b.accel_bias_frd_m_s2)
    assert np.all(
        (np.abs(a.gyro_bias_frd_rad_s) >= 0.001) & (np.abs(a.gyro_bias_frd_rad_s) <= 0.005)
    )
    assert [a.frame_dropped() for _ in range(200)] == [b.frame_dropped() for _ in range(200)]
    first = [_fields(o) for o in _run(sc)]
    assert first == [_fields(o) for o in _run(sc)]  # NaN-free comparison below
    assert any(math.isnan(f[1]) for f in first)  # a dropout happened in these 60 readings


def test_sensors_change_neither_initial_state_wind_nor_the_noise_streams(tmp_path):
    wind = '\n[wind]\nspeed_m_s = [3.0, 8.0]\ndirection_deg = [0.0, 360.0]\nturbulence = "light"\n'
    windy = _sensors(tmp_path, wind)
    both = _sensors(tmp_path, wind + SENSORS)
    w1, w2 = episode_world(windy, 5, 2).wind, episode_world(both, 5, 2).wind
    assert isinstance(w1, WindModel) and isinstance(w2, WindModel)
    assert w1.speed_m_s == w2.speed_m_s and w1.direction_deg == w2.direction_deg
    assert InitialStateSampler(windy, 5).sample(2) == InitialStateSampler(both, 5).sample(2)
    # latency only: every non-image reading is the nominal one, bit for bit
    latency = _sensors(tmp_path, "\n[sensors]\ncamera_latency_ms = [100.0, 100.0]\n")
    nominal, late = _run(load_scenario()), _run(latency)
    assert [_fields(o)[1:] for o in nominal] == [_fields(o)[1:] for o in late]
    # radar faults: the readings they leave alone are the nominal readings
    radar = _sensors(tmp_path, "\n[sensors]\nradar_dropout_prob = 0.3\n")
    faulty = _run(radar)
    kept = [(n.range_m, f.range_m) for n, f in zip(nominal, faulty, strict=True)]
    assert sum(math.isnan(f) for _, f in kept) > 5
    assert all(n == f for n, f in kept if not math.isnan(f))


# --------------------------------------------------------------------------- camera


def test_latency_shows_the_pose_latency_ago_stamped_with_its_exposure(
    vehicle, quiet_cfg, scene, tmp_path
):
    """60 ms = 15 physics steps: the image at step n is the render of the pose at n - 15 and
    ``image_time_s`` is that time; before the flight the initial state is shown."""
    sc = _sensors(tmp_path, "\n[sensors]\ncamera_latency_ms = [60.0, 60.0]\n")
    initial = InitialState((1.0, -2.0, -12.0), (1.5, -1.0, 0.5), (0.05, -0.04, 0.3), (0.0,) * 3)
    sim = Simulator(vehicle, quiet_cfg, scene=scene)
    sim.reset(initial, 0, world=episode_world(sc, 0, 0))
    assert sim.camera_latency_steps == 15
    reference = Camera(scene, quiet_cfg.camera, np.random.default_rng(0))
    first = sim.observe(0)
    assert first.image_time_s == pytest.approx(-0.06)
    np.testing.assert_array_equal(
        first.image, reference.capture(np.asarray(initial.pos_ned_m), initial.quat_wxyz)
    )
    poses = [sim.ground_truth()]
    hover = vehicle.hover_thrust_norm(quiet_cfg.planet)
    cmd = Command(thrust_norm=hover * 0.9, rate_frd_rad_s=np.array([0.3, -0.2, 0.4]))
    for k in range(1, 4):
        for _ in range(quiet_cfg.substeps):
            sim.step_physics(cmd)
            poses.append(sim.ground_truth())
        obs = sim.observe(k)
        then = poses[-1 - 15]
        assert obs.image_time_s == then.time_s == pytest.approx(sim.time_s - 0.06)
        assert obs.imu_time_s == sim.time_s  # the other sensors read now
        np.testing.assert_array_equal(obs.image, reference.capture(then.pos_ned_m, then.quat_wxyz))
        assert not np.array_equal(
            obs.image, reference.capture(poses[-1].pos_ned_m, poses[-1].quat_wxyz)
        )


def test_frame_drop_rate_is_the_configured_probability():
    """200 episodes x 100 frames at p = 0.2: the rate is within 5 binomial sigmas (0.014)."""
    cfg = SensorFaultsConfig(frame_drop_prob=0.2)
    dropped = frames = 0
    for ep in range(200):
        faults = SensorFaults.for_episode(cfg, 11, ep)
        drops = [faults.frame_dropped() for _ in range(101)]
        assert drops[0] is False  # the first frame of a flight is always delivered
        dropped += sum(drops[1:])
        frames += 100
    sigma = math.sqrt(0.2 * 0.8 / frames)
    assert abs(dropped / frames - 0.2) < 5 * sigma


def test_a_dropped_frame_repeats_the_last_delivered_image_and_its_time(
    vehicle, quiet_cfg, scene, tmp_path
):
    sc = _sensors(tmp_path, "\n[sensors]\nframe_drop_prob = 0.5\n")
    initial = InitialState((0.0, 0.0, -10.0), (2.0, 0.0, 0.5), (0.0, 0.0, 0.0), (0.0,) * 3)
    hover = vehicle.hover_thrust_norm(quiet_cfg.planet)
    cmd = Command(thrust_norm=hover, rate_frd_rad_s=np.zeros(3))
    sim = Simulator(vehicle, quiet_cfg, scene=scene)
    sim.reset(initial, 0, world=episode_world(sc, 0, 0))
    last = sim.observe(0)
    repeats = 0
    for k in range(1, 16):
        sim.step(cmd)
        obs = sim.observe(k)
        assert obs.frame_id == k  # the control step's key stays unique
        if obs.image_time_s == sim.time_s:
            assert not np.array_equal(obs.image, last.image)  # a fresh view (moving)
            last = obs
        else:
            repeats += 1
            assert obs.image_time_s == last.image_time_s < sim.time_s
            np.testing.assert_array_equal(obs.image, last.image)
    assert repeats == sim.sensor_faults.frames_dropped > 3


# --------------------------------------------------------------------------- radar and IMU


def test_radar_dropouts_and_outliers_replace_readings_at_their_rates():
    cfg = SensorFaultsConfig(
        radar_dropout_prob=0.1, radar_outlier_prob=0.05, radar_outlier_m=(20.0, 200.0)
    )
    faults = SensorFaults(cfg, np.random.default_rng(3))
    n = 20_000
    out = np.array([faults.radar_reading(10.0, 150.0) for _ in range(n)])
    drop = np.isnan(out)
    spurious = ~drop & (out != 10.0)
    assert abs(drop.mean() - 0.1) < 5 * math.sqrt(0.1 * 0.9 / n)
    p_out = 0.9 * 0.05  # a dropout wins over an outlier
    assert abs(spurious.mean() - p_out) < 5 * math.sqrt(p_out * (1 - p_out) / n)
    assert out[spurious].min() >= 20.0 and out[spurious].max() == 150.0  # clipped at max range
    assert faults.radar_dropouts == drop.sum() and faults.radar_outliers == spurious.sum()


def test_imu_turn_on_bias_shows_in_the_mean_accel_at_rest(vehicle, sim_cfg, tmp_path):
    """On the ground, disarmed, 20 s: the accel minus the nominal run's (same noise streams)
    is the drawn bias to rounding; the mean is (0, 0, -g) + bias within its noise."""
    sc = _sensors(
        tmp_path, "\n[sensors]\naccel_bias_m_s2 = [0.3, 0.5]\ngyro_bias_rad_s = [0.02, 0.03]\n"
    )
    rest = InitialState((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0,) * 3)
    runs = {}
    for name, world in (("nominal", None), ("biased", episode_world(sc, 2, 1))):
        sim = Simulator(vehicle, sim_cfg, render=False)
        sim.reset(rest, 9, world=world)
        obs = []
        for k in range(200):
            sim.step(None)
            obs.append(sim.observe(k))
        runs[name] = (obs, sim.sensor_faults)
    (nominal, _), (biased, faults) = runs["nominal"], runs["biased"]
    bias = faults.accel_bias_frd_m_s2
    assert np.all((np.abs(bias) >= 0.3) & (np.abs(bias) <= 0.5))
    diff = np.array(
        [b.accel_frd_m_s2 - n.accel_frd_m_s2 for n, b in zip(nominal, biased, strict=True)]
    )
    np.testing.assert_allclose(diff, np.tile(bias, (200, 1)), atol=1e-12)
    mean = np.mean([b.accel_frd_m_s2 for b in biased], axis=0)
    g = sim_cfg.planet.gravity_m_s2
    # 5 sigma of white noise over 200 readings plus the bias walk over 20 s
    tol = 5 * (
        sim_cfg.imu.accel_noise_std_m_s2 / math.sqrt(200)
        + sim_cfg.imu.accel_bias_walk_m_s2_sqrt_s * math.sqrt(20)
    )
    np.testing.assert_allclose(mean, np.array([0.0, 0.0, -g]) + bias, atol=tol)
    # ATTITUDE (the estimator's output) carries no gyro bias: the policy's rates are nominal
    assert all(
        np.array_equal(n.rate_frd_rad_s, b.rate_frd_rad_s)
        for n, b in zip(nominal, biased, strict=True)
    )


# --------------------------------------------------------------------------- over MAVLink


def test_sitl_encodes_radar_faults_imu_bias_and_latency_on_the_wire(
    tmp_path, low_scenario, loopback_sitl
):
    """In HOLD (frozen at 5-6 m): DISTANCE_SENSOR is either no return (UINT16_MAX, quality 1,
    what the companion reads as invalid) or the 30 m spurious return, never the true ~5 m;
    HIGHRES_IMU's gyro averages to the drawn bias; camera frames carry the exposure time,
    60 ms before the 10 Hz frame boundary they are sent at."""
    scenario = config_plus(
        tmp_path,
        "\n[sensors]\nradar_dropout_prob = 0.5\nradar_outlier_prob = 1.0\n"
        "radar_outlier_m = [30.0, 30.0]\ngyro_bias_rad_s = [0.02, 0.03]\n"
        "camera_latency_ms = [60.0, 60.0]\n",
        Path(low_scenario),
    )
    p, cfg = loopback_sitl(scenario, tmp_path / "logs", seed=6, hold_timeout_s=30.0)
    with sitl_with_client(p, cfg) as (client, runner):
        client.wait_for("HEARTBEAT", 5.0)
        stamps = [client.next_frame(2.0).time_us for _ in range(12)]
        ranges = [m for m in client.inbox if m.get_type() == "DISTANCE_SENSOR"]
        gyro = [(m.xgyro, m.ygyro, m.zgyro) for m in client.inbox if m.get_type() == "HIGHRES_IMU"]
    sitl = runner.sitl
    assert len(ranges) >= 8 and len(gyro) >= 40
    invalid = [m for m in ranges if m.current_distance == 65_535]
    assert all(m.signal_quality == 1 for m in invalid)
    assert {m.current_distance for m in ranges} == {65_535, 3000}
    assert 0 < len(invalid) < len(ranges)
    bias = sitl.sim.sensor_faults.gyro_bias_frd_rad_s
    noise = sitl.sim_cfg.imu.gyro_noise_std_rad_s
    np.testing.assert_allclose(
        np.mean(gyro, axis=0), bias, atol=5 * noise / math.sqrt(len(gyro)) + 1e-4
    )
    assert all(s % 100_000 == 40_000 for s in stamps)  # boundaries at k x 100 ms, minus 60 ms


def test_lockstep_flight_with_latency_and_drops_answers_every_sent_frame(
    tmp_path, low_scenario, loopback_sitl
):
    """A scripted privileged pilot answers each frame it receives with the frame's stamp (as the
    companion does): lockstep accepts the exposure-time stamp (no lockstep timeout), lost frames
    are not sent (their ids are skipped and logged as events), and the vehicle lands."""
    scenario = config_plus(
        tmp_path,
        "\n[sensors]\ncamera_latency_ms = [100.0, 150.0]\nframe_drop_prob = 0.2\n",
        Path(low_scenario),
    )
    p, cfg = loopback_sitl(scenario, tmp_path / "logs", seed=6, groundtruth=True)
    with sitl_with_client(p, cfg) as (client, runner):
        received = fly_cascade(client, runner)
        runner.finish(20.0)
    sitl = runner.sitl
    assert sitl.results and sitl.results[0].landed
    assert sitl.lockstep_timeouts == 0
    log = read_log(tmp_path / "logs" / "sitl_seed6_ep0000.mcap")
    dropped = {
        int(re.match(r"frame (\d+) lost", e["text"]).group(1))
        for e in log.topic("/events")
        if e["kind"] == "camera_frame_dropped"
    }
    assert len(dropped) > 5
    span = set(range(received[0], received[-1] + 1))
    assert span - set(received) == dropped & span  # exactly the lost frames are missing
    (record,) = list(log.topic("/episode/scenario"))
    assert record["scenario"]["sensors"]["frame_drop_prob"] == 0.2
