"""T_max per planet (and, to come, the ``[vehicle]`` scenario section): config errors, and
nominal flights unchanged bit for bit."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from expert.cascade import CascadeLander
from expert.mpc import MpcExpert
from sitl_sim.config import CONFIG_DIR, PLANETS, load_vehicle
from sitl_sim.env import LandingEnv
from sitl_sim.errors import ConfigError

EARTH = PLANETS["earth"]


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
def test_nominal_flights_are_bit_identical_to_before_t_max_per_planet(scenario, pilot):
    assert _flight_digest(CONFIG_DIR / scenario, pilot) == _NOMINAL_DIGESTS[(scenario, pilot)]


# --------------------------------------------------------------------------- T_max per planet


def _vehicle_file(tmp_path: Path, old: str, new: str) -> Path:
    text = (CONFIG_DIR / "vehicle.toml").read_text()
    assert old in text
    path = tmp_path / "vehicle.toml"
    path.write_text(text.replace(old, new))
    return path


def test_flying_a_planet_without_its_t_max_names_the_file_and_planet(tmp_path):
    path = _vehicle_file(tmp_path, "mars = 25.0", "")
    vehicle = load_vehicle(path)
    assert vehicle.max_total_thrust_n(EARTH) == 25.0
    with pytest.raises(
        ConfigError,
        match=rf"{path}: \[vehicle\.max_total_thrust_n\] has no "
        r"T_max for planet 'mars' \(stated: \['earth'\]\)",
    ):
        LandingEnv(vehicle=path, scenario=CONFIG_DIR / "scenario_mars.toml", render_camera=False)


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        # the old single figure: thrust would silently be the same in any air
        (
            "[vehicle.max_total_thrust_n]",
            "max_total_thrust_n = 25.0\n[vehicle.thrust_notes]",
            r"\[vehicle\] max_total_thrust_n = 25\.0; expected a table "
            r"\[vehicle\.max_total_thrust_n\] with T_max \(N\) per planet",
        ),
        (
            "mars = 25.0",
            "venus = 25.0",
            r"\[vehicle\.max_total_thrust_n\] unknown planet\(s\) \['venus'\]",
        ),
        (
            "mars = 25.0",
            "mars = 0.0",
            r"vehicle\.toml \[vehicle\.max_total_thrust_n\]: mars = 0\.0 is out of range",
        ),
        (
            "[vehicle.max_total_thrust_n]\n",
            "[thrust_by_planet]\n",
            r"missing table \[vehicle\.max_total_thrust_n\]",
        ),
    ],
)
def test_bad_t_max_tables_name_file_and_key(tmp_path, old, new, match):
    with pytest.raises(ConfigError, match=match):
        load_vehicle(_vehicle_file(tmp_path, old, new))
