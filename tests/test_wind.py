"""Wind, Dryden turbulence and 1-cosine gusts (``[wind]``): config checks, the model's
statistics against MIL-F-8785C, the air-relative drag, determinism, and a still-air world that
is exactly what it was before wind existed."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from flights import fly_cascade, sitl_with_client
from helpers import config_plus

from companion.contract import Command
from companion.flightlog import read_log
from expert.cascade import CascadeLander
from sitl_sim.config import CONFIG_DIR, PLANETS
from sitl_sim.env import LandingEnv
from sitl_sim.errors import ConfigError
from sitl_sim.flight_record import groundtruth_from_msg, groundtruth_msg
from sitl_sim.physics.dynamics import Physics, derivative, quat_from_euler, translational_accel_ned
from sitl_sim.physics.wind import (
    TURBULENCE_W20_M_S,
    WindConfig,
    WindModel,
    dryden_low_altitude,
)
from sitl_sim.scenario import InitialState, InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator
from sitl_sim.world import EpisodeWorld

EARTH = PLANETS["earth"]
WIND = """
[wind]
speed_m_s = [3.0, 8.0]
direction_deg = [0.0, 360.0]
turbulence = "moderate"
gust_m_s = [1.0, 3.0]
"""


# --------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    "old,new,match",
    [
        (
            'turbulence = "moderate"',
            'turbulence = "moderate"\nspeeed_m_s = [1.0, 2.0]',
            r"scenario\.toml: \[wind\] unknown key\(s\) \['speeed_m_s'\]; expected \['speed_m_s'",
        ),
        (
            "speed_m_s = [3.0, 8.0]",
            "speed_m_s = [8.0, 3.0]",
            r"scenario\.toml: \[wind\] speed_m_s = \[8\.0, 3\.0\]; expected finite \[lo, hi\] with"
            r" 0 <= lo <= hi <= 50 \(m/s\)",
        ),
        (
            "direction_deg = [0.0, 360.0]",
            "direction_deg = [90.0, 45.0]",
            r"scenario\.toml: \[wind\] direction_deg = \[90\.0, 45\.0\]; expected finite",
        ),
        (
            'turbulence = "moderate"',
            'turbulence = "strong"',
            r"scenario\.toml: \[wind\] turbulence = 'strong'; expected one of \['none', 'light',"
            r" 'moderate', 'severe'\]",
        ),
        (
            'turbulence = "moderate"',
            "turbulence = 2",
            r"scenario\.toml: \[wind\] turbulence = 2; expected one of",
        ),
        (
            "speed_m_s = [3.0, 8.0]",
            "speed_m_s = [-1.0, 8.0]",
            r"scenario\.toml: \[wind\] speed_m_s = \[-1\.0, 8\.0\]; expected finite \[lo, hi\] "
            r"with 0 <= lo <= hi <= 50 \(m/s\)",
        ),
        (
            "gust_m_s = [1.0, 3.0]",
            "gust_m_s = [-0.5, 3.0]",
            r"scenario\.toml: \[wind\] gust_m_s = \[-0\.5, 3\.0\]; expected finite \[lo, hi\] "
            r"with 0 <= lo <= hi <= 30 \(m/s\)",
        ),
        (  # physical bounds: a hurricane is 50 m/s, a gust 30, a direction one turn either way
            "speed_m_s = [3.0, 8.0]",
            "speed_m_s = [200.0, 300.0]",
            r"scenario\.toml: \[wind\] speed_m_s = \[200\.0, 300\.0\]; expected finite "
            r"\[lo, hi\] with 0 <= lo <= hi <= 50 \(m/s\)",
        ),
        (
            "gust_m_s = [1.0, 3.0]",
            "gust_m_s = [1.0, 80.0]",
            r"scenario\.toml: \[wind\] gust_m_s = \[1\.0, 80\.0\]; expected .* <= 30 \(m/s\)",
        ),
        (
            "direction_deg = [0.0, 360.0]",
            "direction_deg = [0, 720]",
            r"scenario\.toml: \[wind\] direction_deg = \[0\.0, 720\.0\]; expected finite "
            r"\[lo, hi\] with -360 <= lo <= hi <= 360 \(deg\)",
        ),
        (
            "speed_m_s = [3.0, 8.0]",
            'speed_m_s = "fast"',
            r"scenario\.toml: \[wind\] speed_m_s = 'fast'; expected \[lo, hi\] \(two numbers\)",
        ),
        (
            "gust_m_s = [1.0, 3.0]",
            "gust_m_s = [1.0, true]",
            r"scenario\.toml: \[wind\] gust_m_s = \[1\.0, True\]; expected \[lo, hi\]",
        ),
        (
            "direction_deg = [0.0, 360.0]\n",
            "",
            r"scenario\.toml: \[wind\] missing key 'direction_deg'; expected \[lo, hi\]",
        ),
    ],
)
def test_bad_wind_sections_name_file_key_expected_and_got(tmp_path, old, new, match):
    assert old in WIND
    with pytest.raises(ConfigError, match=match):
        load_scenario(config_plus(tmp_path, WIND.replace(old, new)))


def test_wind_section_is_typed_and_still_air_scenarios_are_unchanged():
    sc = load_scenario(CONFIG_DIR / "scenario_wind.toml")
    assert sc.wind == WindConfig((3.0, 8.0), (0.0, 360.0), "moderate", (1.0, 3.0))
    assert sc.to_dict()["wind"] == {
        "speed_m_s": [3.0, 8.0],
        "direction_deg": [0.0, 360.0],
        "turbulence": "moderate",
        "gust_m_s": [1.0, 3.0],
    }
    nominal = load_scenario()
    assert nominal.wind is None and "wind" not in nominal.to_dict()  # logs keep their record
    # the initial states do not depend on the wind
    a, b = InitialStateSampler(sc, 4).sample(3), InitialStateSampler(nominal, 4).sample(3)
    assert a == b


# --------------------------------------------------------------------------- the model


def _series(model: WindModel, steps: int, dt: float, pos, vel) -> np.ndarray:
    model.start(pos)
    out = np.empty((steps, 3))
    for k in range(steps):
        out[k] = model.step(dt, k * dt, pos, vel)
    return out


def test_mean_wind_uses_the_from_convention():
    north = WindModel(WindConfig((5.0, 5.0), (0.0, 0.0)), np.random.default_rng(0))
    np.testing.assert_allclose(north.mean_wind_ned_m_s, [-5.0, 0.0, 0.0], atol=1e-12)
    east = WindModel(WindConfig((5.0, 5.0), (90.0, 90.0)), np.random.default_rng(0))
    np.testing.assert_allclose(east.mean_wind_ned_m_s, [0.0, -5.0, 0.0], atol=1e-12)
    drawn = WindModel.for_episode(WindConfig((3.0, 8.0), (10.0, 20.0)), 1, 2)
    assert 3.0 <= drawn.speed_m_s <= 8.0 and 10.0 <= drawn.direction_deg <= 20.0
    assert np.linalg.norm(drawn.mean_wind_ned_m_s) == pytest.approx(drawn.speed_m_s)


def test_no_turbulence_and_no_gusts_is_exactly_the_mean_wind():
    model = WindModel.for_episode(WindConfig((2.0, 6.0), (0.0, 360.0), "none"), 9, 1)
    series = _series(model, 500, 0.004, (0.0, 0.0, -30.0), (1.0, 0.0, 0.5))
    assert np.all(series == model.mean_wind_ned_m_s)
    assert np.all(model.wind_ned_m_s == model.mean_wind_ned_m_s)


def test_same_seed_and_episode_give_the_same_wind_and_another_episode_another():
    cfg = WindConfig((3.0, 8.0), (0.0, 360.0), "severe", (1.0, 3.0))
    pos, vel = (1.0, 2.0, -40.0), (0.5, -0.2, 1.0)
    a = _series(WindModel.for_episode(cfg, 5, 2), 3000, 0.004, pos, vel)
    b = _series(WindModel.for_episode(cfg, 5, 2), 3000, 0.004, pos, vel)
    c = _series(WindModel.for_episode(cfg, 5, 3), 3000, 0.004, pos, vel)
    np.testing.assert_array_equal(a, b)
    assert not np.any(np.all(a == c, axis=1))


def test_dryden_parameters_follow_mil_f_8785c_low_altitude():
    p = dryden_low_altitude(10.0, TURBULENCE_W20_M_S["moderate"])
    assert p.sigma_w_m_s == pytest.approx(1.543)
    assert p.length_w_m == pytest.approx(10.0)
    assert p.length_u_m == p.length_v_m == pytest.approx(67.4, abs=0.05)  # the notes' table
    assert p.sigma_u_m_s == p.sigma_v_m_s == pytest.approx(2.91, abs=0.005)
    clipped = dryden_low_altitude(0.5, TURBULENCE_W20_M_S["moderate"])
    assert clipped == dryden_low_altitude(10 * 0.3048, TURBULENCE_W20_M_S["moderate"])
    assert clipped.length_w_m == pytest.approx(3.048)


def _acf(x: np.ndarray) -> np.ndarray:
    x = x - x.mean()
    f = np.fft.rfft(x, 2 * len(x))
    r = np.fft.irfft(f * np.conj(f))[: len(x)]
    return r / r[0]


def test_moderate_turbulence_has_the_dryden_intensities_and_correlation():
    """5000 s at 10 m and 15 m/s through the air, stepped at 20 Hz (the filters are discretised
    exactly, so the step length does not change the statistics). There tau_u = L_u/V = 4.5 s,
    tau_w = 0.67 s: about 1100 correlation times of u, so a sample sigma has a relative standard
    error of about sqrt(tau/T) = 3 % (Bartlett) — 15 % is five of them — and the 1/e crossing of
    u's autocorrelation (slope -1/(e tau) there) about 5 %: 20 % is four."""
    cfg = WindConfig((5.0, 5.0), (30.0, 30.0), "moderate")
    model = WindModel.for_episode(cfg, 7, 0)
    altitude, airspeed, dt, duration = 10.0, 15.0, 0.05, 5000.0
    psi = math.radians(30.0)
    downwind = np.array([-math.cos(psi), -math.sin(psi), 0.0])
    pos = np.array([0.0, 0.0, -altitude])
    vel = model.mean_wind_ned_m_s + airspeed * downwind
    model.start(pos)
    n = int(duration / dt)
    turb = np.empty((n, 3))
    total = np.empty((n, 3))
    for k in range(n):
        total[k] = model.step(dt, k * dt, pos, vel)
        turb[k] = model.turbulence_wind_axes_m_s
    p = dryden_low_altitude(altitude, TURBULENCE_W20_M_S["moderate"])
    sigma = np.array([p.sigma_u_m_s, p.sigma_v_m_s, p.sigma_w_m_s])
    np.testing.assert_allclose(turb.std(axis=0), sigma, rtol=0.15)
    tau_u = p.length_u_m / airspeed
    crossing = int(np.argmax(_acf(turb[:, 0]) < math.exp(-1.0))) * dt
    assert crossing == pytest.approx(tau_u, rel=0.20)
    # v and w: the Dryden lateral correlation (1 - xi/2L) e^{-xi/L} is e^-1/2 at xi = L
    for axis, length in ((1, p.length_v_m), (2, p.length_w_m)):
        lag = round(length / airspeed / dt)
        assert _acf(turb[:, axis])[lag] == pytest.approx(0.5 * math.exp(-1.0), abs=0.05)
    # the turbulence is rotated into NED about the mean wind: the mean stays the sampled mean
    np.testing.assert_allclose(total.mean(axis=0), model.mean_wind_ned_m_s, atol=0.4)
    along = (total - model.mean_wind_ned_m_s) @ downwind
    np.testing.assert_allclose(along[1:], turb[:-1, 0], atol=1e-9)  # step returns the held wind


def test_gusts_are_1_cosine_along_the_wind_at_the_documented_rate():
    cfg = WindConfig((4.0, 4.0), (200.0, 200.0), "none", (2.0, 2.0))
    model = WindModel.for_episode(cfg, 3, 0)
    dt = 0.01
    series = _series(model, 30000, dt, (0.0, 0.0, -20.0), (0.0, 0.0, 0.0))
    gust = series - model.mean_wind_ned_m_s
    psi = math.radians(200.0)
    downwind = np.array([-math.cos(psi), -math.sin(psi), 0.0])
    speed = gust @ downwind
    np.testing.assert_allclose(gust, np.outer(speed, downwind), atol=1e-12)  # along the wind
    assert speed.min() >= 0.0 and speed.max() == pytest.approx(2.0, abs=1e-3)
    active = speed > 0.0
    starts = np.flatnonzero(active[1:] & ~active[:-1]) * dt
    ends = np.flatnonzero(~active[1:] & active[:-1]) * dt
    assert starts[0] <= 20.0 and len(starts) >= 300.0 / 20.0 - 1
    assert np.all((np.diff(starts) > 10.0 - 2 * dt) & (np.diff(starts) < 20.0 + 2 * dt))
    durations = ends[: len(starts)] - starts[: len(ends)]
    assert np.all((durations > 1.0 - 2 * dt) & (durations < 3.0 + 2 * dt))


# --------------------------------------------------------------------------- physics


def test_drag_acts_on_the_air_relative_velocity(vehicle):
    phys = Physics(vehicle, EARTH)
    q = tuple(quat_from_euler(0.1, -0.2, 0.7))
    wind = (-4.0, 2.5, 0.3)
    at_rest = translational_accel_ned(q, (0.0, 0.0, 0.0), 9.0, phys)
    assert translational_accel_ned(q, (0.0, 0.0, 0.0), 9.0, phys, wind) != at_rest
    # a vehicle at rest over the ground in the wind = a vehicle moving at -wind in still air
    assert translational_accel_ned(q, (0.0, 0.0, 0.0), 9.0, phys, wind) == (
        translational_accel_ned(q, (4.0, -2.5, -0.3), 9.0, phys)
    )
    # None is still air, computed as before (no zero subtracted)
    v = (1.0, -2.0, 0.5)
    assert translational_accel_ned(q, v, 9.0, phys, None) == translational_accel_ned(
        q, v, 9.0, phys
    )
    x = [0.0, 0.0, -10.0, 0.0, 0.0, 0.0, *q, 0.1, 0.0, 0.0, 2.0, 2.0, 2.5, 2.5]
    d = derivative(x, [2.0] * 4, phys, wind)
    assert tuple(d[3:6]) == translational_accel_ned(q, (4.0, -2.5, -0.3), 9.0, phys)


def test_a_hovering_vehicle_drifts_downwind_in_a_steady_wind(vehicle, quiet_cfg):
    sim = Simulator(vehicle, quiet_cfg, render=False)
    initial = InitialState((0.0, 0.0, -20.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    wind = WindModel(WindConfig((6.0, 6.0), (0.0, 0.0)), np.random.default_rng(0))
    sim.reset(initial, 0, world=EpisodeWorld(wind=wind))
    truth = sim.ground_truth()
    np.testing.assert_array_equal(truth.wind_ned_m_s, [-6.0, 0.0, 0.0])
    hover = vehicle.hover_thrust_norm(EARTH)
    for _ in range(10):
        sim.step(Command(hover, np.zeros(3)))
    truth = sim.ground_truth()
    assert truth.vel_ned_m_s[0] < -0.1 and abs(truth.vel_ned_m_s[1]) < 1e-9  # pushed south


# --------------------------------------------------------------------------- the simulator


def _fly(vehicle, sim_cfg, wind: WindModel | None, *, new_call: bool = True) -> list:
    sim = Simulator(vehicle, sim_cfg, render=False)
    initial = InitialState((1.0, -2.0, -30.0), (0.5, 0.0, 0.2), (0.02, -0.01, 0.3), (0.0,) * 3)
    seed = np.random.SeedSequence([11, 4])
    if new_call:
        sim.reset(initial, seed, world=EpisodeWorld(wind=wind))
    else:
        sim.reset(initial, seed)  # the call signature from before wind existed
    rng = np.random.default_rng(5)
    out = []
    for _ in range(30):
        cmd = Command(0.4 + 0.02 * rng.standard_normal(), rng.uniform(-0.3, 0.3, 3))
        sim.step(cmd)
        gt = sim.ground_truth()
        obs = sim.observe(truth=gt)
        out.append((gt, obs.accel_frd_m_s2))
    return out


def _same(a: list, b: list) -> bool:
    for (ga, ia), (gb, ib) in zip(a, b, strict=True):
        for name in ("pos_ned_m", "vel_ned_m_s", "quat_wxyz", "accel_ned_m_s2", "wind_ned_m_s"):
            va, vb = getattr(ga, name), getattr(gb, name)
            if (va is None) != (vb is None) or (va is not None and not np.array_equal(va, vb)):
                return False
        if not np.array_equal(ia, ib):
            return False
    return True


def test_same_seed_and_episode_fly_the_same_flight_bit_for_bit(vehicle, sim_cfg):
    cfg = load_scenario(CONFIG_DIR / "scenario_wind.toml").wind
    assert cfg is not None
    a = _fly(vehicle, sim_cfg, WindModel.for_episode(cfg, 11, 4))
    b = _fly(vehicle, sim_cfg, WindModel.for_episode(cfg, 11, 4))
    assert _same(a, b)
    assert a[-1][0].wind_ned_m_s is not None
    c = _fly(vehicle, sim_cfg, WindModel.for_episode(cfg, 11, 5))
    assert not np.array_equal(a[-1][0].pos_ned_m, c[-1][0].pos_ned_m)


def test_still_air_is_the_flight_of_the_old_call_and_carries_no_wind(vehicle, sim_cfg):
    new, old = _fly(vehicle, sim_cfg, None), _fly(vehicle, sim_cfg, None, new_call=False)
    assert _same(new, old)
    assert all(gt.wind_ned_m_s is None for gt, _ in new)
    msg = groundtruth_msg(new[-1][0], 3)
    assert "wind_ned_m_s" not in msg  # still-air logs keep their exact record
    assert groundtruth_from_msg({"time_s": 1.0, **msg}).wind_ned_m_s is None


def test_ground_truth_log_record_carries_the_wind(vehicle, sim_cfg):
    cfg = WindConfig((3.0, 3.0), (45.0, 45.0), "light")
    gt = _fly(vehicle, sim_cfg, WindModel.for_episode(cfg, 1, 0))[-1][0]
    msg = groundtruth_msg(gt, 7)
    np.testing.assert_array_equal(msg["wind_ned_m_s"], gt.wind_ned_m_s)
    back = groundtruth_from_msg({"time_s": gt.time_s, **msg})
    np.testing.assert_array_equal(back.wind_ned_m_s, gt.wind_ned_m_s)


def _env_flight(scenario, steps: int) -> list:
    env = LandingEnv(scenario=scenario, render_camera=False)
    try:
        env.reset(seed=2, options={"episode_index": 1})
        lander = CascadeLander(env.vehicle, env.sim_config.planet)
        out = []
        for _ in range(steps):
            gt = env.simulator.ground_truth()
            cmd, _ = lander.act(None, gt, None)
            env.step(cmd.as_array())
            out.append(env.simulator.ground_truth())
        return out
    finally:
        env.close()


def test_env_flies_the_scenario_wind_of_seed_and_episode(tmp_path):
    path = str(CONFIG_DIR / "scenario_wind.toml")
    a, b = _env_flight(path, 40), _env_flight(path, 40)
    for ga, gb in zip(a, b, strict=True):
        np.testing.assert_array_equal(ga.pos_ned_m, gb.pos_ned_m)
        np.testing.assert_array_equal(ga.wind_ned_m_s, gb.wind_ned_m_s)
    cfg = load_scenario(path).wind
    assert cfg is not None
    expected = WindModel.for_episode(cfg, 2, 1)
    np.testing.assert_allclose(
        np.mean([g.wind_ned_m_s for g in a], axis=0)[:2],
        expected.mean_wind_ned_m_s[:2],
        atol=3 * 3.1,  # 4 s of moderate turbulence about the episode's mean wind
    )
    still = _env_flight(None, 3)
    assert all(g.wind_ned_m_s is None for g in still)


def test_sitl_flies_in_the_scenario_wind_and_logs_it(tmp_path, low_scenario, loopback_sitl):
    """One lockstep MAVLink flight from 5-6 m in wind: the log's ground truth carries the wind of
    (seed, episode), restarted at the take-over, and its scenario record the [wind] section."""
    scenario = tmp_path / "low_wind.toml"
    scenario.write_text(
        Path(low_scenario).read_text()
        + '\n[wind]\nspeed_m_s = [2.0, 3.0]\ndirection_deg = [0.0, 360.0]\nturbulence = "light"\n'
    )
    p, cfg = loopback_sitl(scenario, tmp_path / "logs", groundtruth=True, seed=6)
    with sitl_with_client(p, cfg) as (client, runner):
        fly_cascade(client, runner)
        runner.finish(20.0)  # re-raises whatever the SITL raised
    sitl = runner.sitl
    assert sitl.results and sitl.results[0].landed
    log = read_log(tmp_path / "logs" / "sitl_seed6_ep0000.mcap")
    (record,) = list(log.topic("/episode/scenario"))
    assert record["scenario"]["wind"]["turbulence"] == "light"
    flying = [m for m in log.topic("/groundtruth/state") if m["flying"]]
    assert len(flying) > 20 and all("wind_ned_m_s" in m for m in flying)
    fresh = WindModel.for_episode(load_scenario(scenario).wind, 6, 0)
    fresh.start(flying[0]["pos_ned_m"])
    np.testing.assert_allclose(flying[0]["wind_ned_m_s"], fresh.wind_ned_m_s, rtol=1e-12)


def test_env_info_groundtruth_carries_the_wind_only_in_wind():
    windy = LandingEnv(scenario=str(CONFIG_DIR / "scenario_wind.toml"), render_camera=False)
    still = LandingEnv(render_camera=False)
    try:
        _, info = windy.reset(seed=2)
        np.testing.assert_array_equal(
            info["groundtruth"]["wind_ned_m_s"], windy.simulator.ground_truth().wind_ned_m_s
        )
        _, info = still.reset(seed=2)
        assert "wind_ned_m_s" not in info["groundtruth"]
    finally:
        windy.close()
        still.close()
