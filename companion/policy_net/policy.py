"""The learned policy: networks, estimator and geometry put together behind ``act``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from companion.contract import Command, Observation
from companion.policy_net.config import CheckpointError, NetConfig
from companion.policy_net.estimator import EstimatorState, PadEstimator
from companion.policy_net.geometry import control_features, position_from_bearing
from companion.policy_net.networks import ControlLSTM, PerceptionCNN

__all__ = ["LearnedPolicy", "PolicyState"]


@dataclass(frozen=True)
class PolicyState:
    """Recurrent state of a :class:`LearnedPolicy` (never mutated in place)."""

    lstm: tuple[torch.Tensor, torch.Tensor]
    estimator: EstimatorState | None = None
    last_perception: np.ndarray | None = None
    """The CNN's last raw output (tan_right, tan_forward, visibility logit), for logs."""


@dataclass
class LearnedPolicy:
    """A trained policy: ``initial_state()`` / ``act(observation, groundtruth, state)``.

    ``groundtruth`` (a :class:`companion.contract.GroundTruth`: the simulator's, or the
    companion's ODOMETRY record) is read only by privileged policies. Vision policies ignore it
    (pass ``None`` on hardware).
    """

    config: NetConfig
    control: ControlLSTM
    perception: PerceptionCNN | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.control.eval()
        if self.perception is not None:
            self.perception.eval()
        if self.config.kind == "vision" and self.perception is None:
            raise CheckpointError("a vision policy needs its perception network")
        self._estimator = PadEstimator(self.config)

    @property
    def privileged(self) -> bool:
        return self.config.kind == "privileged"

    def initial_state(self) -> PolicyState:
        est = None if self.privileged else self._estimator.initial_state()
        return PolicyState(lstm=self.control.zero_state(1), estimator=est)

    def perceive(self, image: np.ndarray) -> np.ndarray:
        """The CNN's raw output for one image: (tan_right, tan_forward, visibility logit)."""
        assert self.perception is not None
        with torch.inference_mode():
            out = self.perception(torch.from_numpy(np.array(image, dtype=np.uint8))[None])
        return out[0].numpy().astype(float)

    def features(
        self, observation: Observation, groundtruth: Any, state: PolicyState
    ) -> tuple[np.ndarray, PolicyState]:
        """The controller input for this step and the state with the estimator advanced."""
        if self.privileged:
            if groundtruth is None:
                raise ValueError(
                    "privileged policy: needs ground truth (position/velocity); it cannot fly "
                    "on hardware — use a vision policy"
                )
            feats = control_features(
                np.asarray(groundtruth.pos_ned_m, float),
                np.asarray(groundtruth.vel_ned_m_s, float),
                observation.attitude_rad,
                observation.rate_frd_rad_s,
                observation.accel_frd_m_s2,
                1.0,
            )
            return feats, state
        raw = self.perceive(observation.image)
        return self.vision_features(
            raw,
            observation.attitude_rad,
            observation.rate_frd_rad_s,
            observation.accel_frd_m_s2,
            observation.range_m,
            state,
        )

    def vision_features(
        self,
        raw: np.ndarray,
        attitude_rad: np.ndarray,
        rate_frd_rad_s: np.ndarray,
        accel_frd_m_s2: np.ndarray,
        range_m: float,
        state: PolicyState,
    ) -> tuple[np.ndarray, PolicyState]:
        """Controller input from the CNN's output (``perceive``) and the sensors; estimator step.

        Split from :meth:`features` so training can batch the CNN over a recorded flight and
        still run exactly this code for the rest.
        """
        vis = 1.0 / (1.0 + math.exp(-float(np.clip(raw[2], -30, 30))))
        fix = position_from_bearing(float(raw[0]), float(raw[1]), attitude_rad, range_m)
        seen = vis >= self.config.visibility_threshold
        assert state.estimator is not None
        est = self._estimator.step(state.estimator, fix, seen, attitude_rad, accel_frd_m_s2)
        feats = control_features(
            est.x[:, 0], est.x[:, 1], attitude_rad, rate_frd_rad_s, accel_frd_m_s2, vis
        )
        return feats, replace(state, estimator=est, last_perception=raw)

    def act(
        self, observation: Observation, groundtruth: Any, state: PolicyState
    ) -> tuple[Command, PolicyState]:
        feats, state = self.features(observation, groundtruth, state)
        if not np.all(np.isfinite(feats)):
            raise ValueError(f"policy input not finite at frame {observation.frame_id}: {feats}")
        with torch.inference_mode():
            out, lstm = self.control(torch.from_numpy(feats)[None, None], state.lstm)
        cmd = out[0, 0].numpy().astype(float)
        if not np.all(np.isfinite(cmd)):
            raise ValueError(f"policy output not finite at frame {observation.frame_id}: {cmd}")
        command = Command(thrust_norm=float(np.clip(cmd[0], 0.0, 1.0)), rate_frd_rad_s=cmd[1:])
        return command, replace(state, lstm=lstm)
