"""``visland/Landing-v0``: the landing task as a gymnasium environment (in process, lockstep).

* action ``float32[4] = [thrust_norm, p, q, r]`` — the Command contract (thrust fraction of
  T_max, 25 N for the vehicle file, FRD body rates in rad/s), one per camera frame (10 Hz);
* observation ``dict``: ``image`` (128, 128) uint8, ``attitude_rad`` (3,), ``rate_frd_rad_s``
  (3,), ``range_m`` (1,) (``-1`` when the radar reports invalid), ``accel_frd_m_s2`` (3,); a
  ``[camera]`` larger than 128 x 128 renders at full resolution and hands on the window the
  simulator is aimed at (:mod:`sitl_sim.full_res`; default the centred 45° view);
* ``info["groundtruth"]``: ``pos_ned_m``, ``vel_ned_m_s``, ``quat_wxyz``, ``rate_frd_rad_s``
  (+ ``wind_ned_m_s`` in wind) (privileged: for experts, labels and metrics, never in the
  observation);
* ``info["airframe"]`` (only with a ``[vehicle]`` scenario section): the episode's airframe
  factors; :attr:`LandingEnv.episode_vehicle` is the vehicle they make (privileged too);
  ``info["visual"]`` (only with ``[visual]``, or a ``[pad]`` other than the paper's pad): the
  episode's drawn look (terrain or ground picture, seed, sun, ...); ``info["pad"]`` (only with
  ``[pad]``): the episode's pad design (name, file, size);
* the episode terminates at the first ground contact (``info["result"]`` then holds the landing
  metrics) and is truncated at ``episode_timeout_s``;
* reward: 0 during flight; at the end ``-(landing error [m] + touchdown speed [m/s])``, or
  ``-(horizontal distance + 10)`` at a timeout. visland learns by imitation; the reward is there
  so RL baselines have a sensible target.

``reset(seed=s)`` starts the episode sequence of seed ``s`` (episode 0 of the scenario sampler);
each later ``reset()`` without a seed takes the next episode; ``options={"episode_index": i}``
takes episode ``i`` of the seed, ``options={"initial_state": st}`` starts from a given
:class:`~sitl_sim.scenario.InitialState`. Same seed, same actions: identical
observations, bit for bit. Episode ``i`` of seed ``s`` flies the world
:func:`sitl_sim.world.episode_world` draws for ``(scenario, s, i)`` (wind, airframe, and every
other scenario section), also with a given initial state.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from companion.contract import IMAGE_SIZE_PX, Command, ContractError, GroundTruth, Observation
from sitl_sim.config import SimConfig, VehicleConfig, load_sim, load_vehicle
from sitl_sim.full_res import make_simulator
from sitl_sim.gym_registration import ENV_ID
from sitl_sim.metrics import EpisodeResult
from sitl_sim.physics.airframe import AirframeScales, check_airframe_can_hover
from sitl_sim.scenario import InitialState, InitialStateSampler, Scenario, load_scenario
from sitl_sim.simulator import Simulator
from sitl_sim.world import episode_world

__all__ = ["ENV_ID", "LandingEnv", "observation_to_dict"]

INVALID_RANGE = -1.0


def observation_to_dict(obs: Observation) -> dict[str, np.ndarray]:
    """The gymnasium observation dict of an Observation."""
    rng = obs.range_m if math.isfinite(obs.range_m) else INVALID_RANGE
    return {
        "image": obs.image,
        "attitude_rad": obs.attitude_rad.astype(np.float32),
        "rate_frd_rad_s": obs.rate_frd_rad_s.astype(np.float32),
        "range_m": np.array([rng], dtype=np.float32),
        "accel_frd_m_s2": obs.accel_frd_m_s2.astype(np.float32),
    }


class LandingEnv(gym.Env):
    """Vision-based landing from the paper's initial-state distribution."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        vehicle: VehicleConfig | str | Path | None = None,
        sim: SimConfig | str | Path | None = None,
        scenario: Scenario | str | Path | None = None,
        *,
        render_camera: bool = True,
        render_mode: str | None = None,
    ) -> None:
        self.vehicle = vehicle if isinstance(vehicle, VehicleConfig) else load_vehicle(vehicle)
        sim_cfg = sim if isinstance(sim, SimConfig) else load_sim(sim)
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        self.sim_config = sim_cfg.with_planet(self.scenario.world)
        if self.scenario.vehicle is not None:
            check_airframe_can_hover(self.scenario.vehicle, self.vehicle, self.scenario.world)
        self.render_mode = render_mode
        self._sim = make_simulator(self.vehicle, self.sim_config, render=render_camera)
        rc = self.vehicle.rate_controller
        hi = np.array([1.0, *rc.max_rate_rad_s], dtype=np.float32)
        lo = np.array([0.0, *(-r for r in rc.max_rate_rad_s)], dtype=np.float32)
        self.action_space = spaces.Box(lo, hi, dtype=np.float32)
        big = np.float32(1e4)
        self.observation_space = spaces.Dict(
            {
                "image": spaces.Box(0, 255, (IMAGE_SIZE_PX, IMAGE_SIZE_PX), dtype=np.uint8),
                "attitude_rad": spaces.Box(-np.pi, np.pi, (3,), dtype=np.float32),
                "rate_frd_rad_s": spaces.Box(-big, big, (3,), dtype=np.float32),
                "range_m": spaces.Box(
                    INVALID_RANGE, self.sim_config.radar.max_range_m * 2, (1,), dtype=np.float32
                ),
                "accel_frd_m_s2": spaces.Box(-big, big, (3,), dtype=np.float32),
            }
        )
        self._sampler: InitialStateSampler | None = None
        self._seed = 0
        self._episode_index = -1
        self._frame = 0
        self._last_image: np.ndarray | None = None
        self._airframe: AirframeScales | None = None
        self._drawn: dict[str, Any] = {}
        self.result: EpisodeResult | None = None

    # ------------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        opts = options or {}
        if seed is not None or self._sampler is None:
            self._seed = int(seed) if seed is not None else int(self.np_random.integers(2**31))
            self._sampler = InitialStateSampler(self.scenario, self._seed)
            self._episode_index = 0
        else:
            self._episode_index += 1
        if "episode_index" in opts:  # jump to episode i of the seed (parallel workers, resume)
            self._episode_index = int(opts["episode_index"])
        initial = opts.get("initial_state")
        if initial is None:
            initial = self._sampler.sample(self._episode_index)
        elif not isinstance(initial, InitialState):
            raise TypeError(
                f"options['initial_state'] must be an InitialState, got {type(initial).__name__}"
            )
        self.initial_state = initial
        world = episode_world(self.scenario, self._seed, self._episode_index)
        self._airframe = world.airframe
        self._drawn = world.record()
        self._sim.reset(
            initial, np.random.SeedSequence([self._seed, self._episode_index]), world=world
        )
        self._frame = 0
        self.result = None
        truth = self._sim.ground_truth()
        obs = self._sim.observe(frame_id=0, truth=truth)
        self._last_image = obs.image
        return observation_to_dict(obs), self._info(truth)

    def step(self, action):
        if self.result is not None:
            raise gym.error.ResetNeeded("the episode has ended: call reset() before step()")
        act = np.asarray(action, dtype=np.float64)
        if act.shape != (4,):
            raise ContractError(
                f"action: expected shape (4,) [thrust_norm, p, q, r], got {act.shape}"
            )
        bad = [
            n
            for n, v in zip(("thrust_norm", "p", "q", "r"), act, strict=True)
            if not math.isfinite(v)
        ]
        if bad:
            raise ContractError(
                f"action: non-finite {bad} in {act.tolist()}; expected finite values"
            )
        act = np.clip(act, self.action_space.low, self.action_space.high)
        contact = self._sim.step(Command.from_array(act))
        self._frame += 1
        truth = self._sim.ground_truth()
        terminated = contact is not None
        truncated = False
        reward = 0.0
        if terminated:
            self.result = EpisodeResult.from_contact(contact)
            reward = -(self.result.landing_error_m + self.result.touchdown_speed_m_s)
        elif truth.time_s >= self.sim_config.episode_timeout_s - 1e-9:
            truncated = True
            self.result = EpisodeResult.timeout(truth.time_s, *truth.pad_relative)
            reward = -(self.result.landing_error_m + 10.0)
        obs = self._sim.observe(frame_id=self._frame, truth=truth)
        self._last_image = obs.image
        return observation_to_dict(obs), reward, terminated, truncated, self._info(truth)

    def render(self):
        if self._last_image is None:
            return None
        return np.repeat(self._last_image[..., None], 3, axis=2)

    def close(self) -> None:
        self._sim.close()

    # ------------------------------------------------------------------ helpers

    @property
    def simulator(self) -> Simulator:
        return self._sim

    @property
    def episode_vehicle(self) -> VehicleConfig:
        """The vehicle the current episode flies: :attr:`vehicle` (the vehicle file) scaled by
        the episode's ``[vehicle]`` factors, or :attr:`vehicle` itself (privileged: a
        model-based expert flies it; a deployable policy never reads it)."""
        return self._sim.episode_vehicle

    @property
    def drawn(self) -> dict[str, Any]:
        """What the current episode's world drew (:meth:`sitl_sim.world.EpisodeWorld.record`:
        ``airframe``, ``visual``, ``pad``, ``site``; empty for the nominal world)."""
        return self._drawn

    @property
    def airframe(self) -> AirframeScales | None:
        """The current episode's airframe factors (None: no ``[vehicle]`` section)."""
        return self._airframe

    def _info(self, truth: GroundTruth) -> dict[str, Any]:
        info: dict[str, Any] = {
            "groundtruth": truth.as_dict(),
            "time_s": truth.time_s,
            "frame_id": self._frame,
            "episode_index": self._episode_index,
        }
        info.update(self._drawn)  # airframe / visual draws; nominal episodes' info is unchanged
        if self.result is not None:
            info["result"] = self.result.to_dict()
        return info
