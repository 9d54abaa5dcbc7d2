"""The gymnasium env: API compliance, determinism, privileged info kept out of observations."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import sitl_sim  # noqa: F401  (registers visland/Landing-v0)
from companion.contract import ContractError
from expert.cascade import CascadeLander
from sitl_sim.env import ENV_ID, LandingEnv


@pytest.fixture()
def env():
    e = LandingEnv()
    yield e
    e.close()


def test_registered_and_passes_gymnasium_check_env():
    e = gym.make(ENV_ID)
    try:
        check_env(e.unwrapped, skip_render_check=True)
    finally:
        e.close()


def test_observation_has_no_ground_truth(env):
    obs, info = env.reset(seed=0)
    assert set(obs) == {"image", "attitude_rad", "rate_frd_rad_s", "range_m", "accel_frd_m_s2"}
    assert obs["image"].shape == (128, 128) and obs["image"].dtype == np.uint8
    assert set(info["groundtruth"]) == {"pos_ned_m", "vel_ned_m_s", "quat_wxyz", "rate_frd_rad_s"}
    assert -info["groundtruth"]["pos_ned_m"][2] == pytest.approx(obs["range_m"][0], rel=0.05)


def _rollout(seed: int, steps: int) -> list[dict[str, np.ndarray]]:
    e = LandingEnv()
    try:
        obs, _ = e.reset(seed=seed)
        out = [obs]
        rng = np.random.default_rng(99)
        for _ in range(steps):
            a = np.array([0.42, *rng.uniform(-0.3, 0.3, 3)], dtype=np.float32)
            obs, *_ = e.step(a)
            out.append(obs)
        return out
    finally:
        e.close()


def test_same_seed_same_observations_bit_for_bit():
    a, b = _rollout(5, 15), _rollout(5, 15)
    for oa, ob in zip(a, b, strict=True):
        for k in oa:
            np.testing.assert_array_equal(oa[k], ob[k])
    c = _rollout(6, 2)
    assert not np.array_equal(a[0]["image"], c[0]["image"])


def test_episode_ends_at_touchdown_with_a_result(env):
    pilot = CascadeLander(env.vehicle, env.sim_config.planet)
    _, info = env.reset(seed=2)
    for _ in range(2000):
        gt = info["groundtruth"]
        cmd = pilot.command(gt["pos_ned_m"], gt["vel_ned_m_s"], gt["quat_wxyz"])
        _, reward, terminated, truncated, info = env.step(cmd.as_array())
        if terminated or truncated:
            break
    assert terminated and not truncated
    res = info["result"]
    assert res["landed"] and res["success"]
    assert res["landing_error_m"] < 0.2 and res["touchdown_speed_m_s"] < 1.0
    assert reward == pytest.approx(-(res["landing_error_m"] + res["touchdown_speed_m_s"]))
    with pytest.raises(gym.error.ResetNeeded):
        env.step(np.array([0.5, 0, 0, 0], dtype=np.float32))


def test_timeout_truncates(vehicle, sim_cfg):
    from dataclasses import replace

    e = LandingEnv(sim=replace(sim_cfg, episode_timeout_s=1.0), render_camera=False)
    try:
        e.reset(seed=0)
        for _ in range(10):
            _, _, terminated, truncated, info = e.step(np.array([0.4, 0, 0, 0], np.float32))
        assert truncated and not terminated and not info["result"]["success"]
    finally:
        e.close()


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_action_is_a_typed_error_naming_the_field(env, bad):
    env.reset(seed=0)
    with pytest.raises(ContractError, match=r"non-finite \['q'\]"):
        env.step(np.array([0.4, 0.0, bad, 0.0], dtype=np.float32))


def test_wrong_action_shape_is_a_typed_error(env):
    env.reset(seed=0)
    with pytest.raises(ContractError, match=r"expected shape \(4,\)"):
        env.step(np.zeros(3, dtype=np.float32))


def test_mars_profile_from_the_scenario(tmp_path):
    e = LandingEnv(scenario="configs/scenario_mars.toml", render_camera=False)
    try:
        assert e.sim_config.planet.name == "mars"
        assert e.vehicle.hover_thrust_norm(e.sim_config.planet) == pytest.approx(3.71 / 25)
    finally:
        e.close()
