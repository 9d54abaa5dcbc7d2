"""The learned landing policy: perception CNN, pad-relative state estimator, LSTM controller.

This package is deployable (numpy + torch only) and is what both training and the companion
process run, so the network that was trained is bit for bit the network that flies.

=================  ===============================================================  =====
module             its one job                                                      torch
=================  ===============================================================  =====
``config``         :class:`NetConfig` (stored in checkpoints), :class:`CheckpointError`  no
``geometry``       pad position from a bearing, the controller's input features      no
``estimator``      :class:`PadEstimator`: Kalman filter of position and velocity     no
``guard``          :class:`LandingGuard`: never land blind (:class:`PadNotFound`)     no
``core``           :class:`PolicyCore`: all but the networks behind ``act``           no
``networks``       :class:`PerceptionCNN` and :class:`ControlLSTM`                   yes
``policy``         :class:`LearnedPolicy`: ``PolicyCore`` over the torch networks    yes
``checkpoint``     save a checkpoint, load it as networks or as a policy             yes
=================  ===============================================================  =====

Every public name is importable from here (``from companion.policy_net import load_policy``);
the torch ones are imported on first use, so the geometry, the estimator, the config and the
policy core (``from companion.policy_net import PadEstimator``) load without torch — the ONNX
runtime (:mod:`companion.onnx_runtime`) flies ``PolicyCore`` on a board with no torch.

Pipeline of the *vision* policy, one call per camera frame (paper Fig. 2, with the CNN's output
given a geometric meaning)::

    image ──PerceptionCNN──▶ pad bearing (tan right, tan forward) + visibility
    bearing + attitude + radar range ──geometry──▶ vehicle position relative to the pad (NED)
    position + IMU specific force ──PadEstimator (Kalman)──▶ position, velocity (NED)
    features(position, velocity, attitude, rates, specific force) ──ControlLSTM──▶ Command

The *privileged* policy (the paper's LSTM-only rows) skips the first three lines and reads
position and velocity from ground truth; everything after is the same network, so stage 3 of
the schedule starts the vision policy from the privileged controller.

Why a bearing: a keypoint in the image is altitude-invariant and translation-equivariant, so a
small CNN (soft-argmax head) learns it from few images; the radar gives the scale. The vehicle
position in metres then follows from geometry instead of being memorised.

Checkpoints (``save_checkpoint`` / ``load_policy``) are plain ``torch.save`` dicts of tensors and
JSON-able values, loaded with ``weights_only=True`` (no code runs on load), and carry their
network config, the feature normalisation, training provenance and git commit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from companion.lazy import lazy_exports
from companion.policy_net.config import ESTIMATOR_FIELDS, CheckpointError, NetConfig
from companion.policy_net.core import PolicyCore, PolicyState, attitude_at
from companion.policy_net.estimator import EstimatorState, PadEstimator
from companion.policy_net.geometry import (
    FEATURE_NAMES,
    control_features,
    feature_names,
    position_from_bearing,
    rotation_zyx,
)
from companion.policy_net.guard import GuardState, LandingGuard, PadNotFound

if TYPE_CHECKING:
    from companion.policy_net.checkpoint import (
        CHECKPOINT_FORMAT,
        load_networks,
        load_policy,
        save_checkpoint,
        untrained_policy,
    )
    from companion.policy_net.networks import ControlLSTM, PerceptionCNN
    from companion.policy_net.policy import LearnedPolicy

__all__ = [
    "CHECKPOINT_FORMAT",
    "ESTIMATOR_FIELDS",
    "FEATURE_NAMES",
    "CheckpointError",
    "ControlLSTM",
    "EstimatorState",
    "GuardState",
    "LandingGuard",
    "LearnedPolicy",
    "NetConfig",
    "PadEstimator",
    "PadNotFound",
    "PerceptionCNN",
    "PolicyCore",
    "PolicyState",
    "attitude_at",
    "control_features",
    "feature_names",
    "load_networks",
    "load_policy",
    "position_from_bearing",
    "rotation_zyx",
    "save_checkpoint",
    "untrained_policy",
]

_TORCH_NAMES = {
    "CHECKPOINT_FORMAT": "checkpoint",
    "load_networks": "checkpoint",
    "load_policy": "checkpoint",
    "save_checkpoint": "checkpoint",
    "untrained_policy": "checkpoint",
    "ControlLSTM": "networks",
    "PerceptionCNN": "networks",
    "LearnedPolicy": "policy",
}
"""The public names whose modules import torch: imported on first access (PEP 562)."""


__getattr__, __dir__ = lazy_exports(__name__, _TORCH_NAMES, __all__)
