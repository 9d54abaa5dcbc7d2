"""The learned policy in torch: :class:`PolicyCore` over :class:`PerceptionCNN` and
:class:`ControlLSTM` (training, and the companion's ``torch`` runtime)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from companion.policy_net.config import CheckpointError, NetConfig
from companion.policy_net.core import PolicyCore, PolicyState, attitude_at
from companion.policy_net.networks import ControlLSTM, PerceptionCNN

__all__ = ["LearnedPolicy", "PolicyState", "attitude_at"]


@dataclass
class LearnedPolicy(PolicyCore):
    """A trained policy: ``initial_state()`` / ``act(observation, groundtruth, state)`` (see
    :class:`PolicyCore`), its networks in torch."""

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
        self._init_core()

    def perceive(self, image: np.ndarray) -> np.ndarray:
        assert self.perception is not None
        with torch.inference_mode():
            out = self.perception(torch.from_numpy(np.array(image, dtype=np.uint8))[None])
        return out[0].numpy().astype(float)

    def zero_state(self) -> tuple[torch.Tensor, ...]:
        return tuple(self.control.zero_state(1))

    def control_step(
        self, features: np.ndarray, state: tuple[torch.Tensor, ...]
    ) -> tuple[np.ndarray, tuple[torch.Tensor, ...]]:
        with torch.inference_mode():
            out, lstm = self.control(torch.from_numpy(features)[None, None], state)
        return out[0, 0].numpy(), lstm
