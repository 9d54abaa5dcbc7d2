"""The learned landing policy: perception CNN, pad-relative state estimator, LSTM controller.

This module is deployable (numpy + torch only) and is what both training and the companion
process run, so the network that was trained is bit for bit the network that flies.

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

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from companion.contract import CAMERA_FOV_DEG, IMAGE_SIZE_PX, Command, Observation

__all__ = [
    "CHECKPOINT_FORMAT",
    "FEATURE_NAMES",
    "CheckpointError",
    "ControlLSTM",
    "EstimatorState",
    "LearnedPolicy",
    "NetConfig",
    "PadEstimator",
    "PerceptionCNN",
    "control_features",
    "load_policy",
    "position_from_bearing",
    "rotation_zyx",
    "save_checkpoint",
    "untrained_policy",
]

CHECKPOINT_FORMAT = "visland-policy"
CHECKPOINT_VERSION = 1

FEATURE_NAMES = (
    "x_h/10",
    "y_h/10",
    "alt/50",
    "min(alt,5)/5",
    "x_h/(alt+1)",
    "y_h/(alt+1)",
    "vx_h/3",
    "vy_h/3",
    "vz/3",
    "roll",
    "pitch",
    "p",
    "q",
    "r",
    "fx/g0",
    "fy/g0",
    "fz/g0",
    "visibility",
)
"""The controller's inputs, in order (``x_h``/``y_h``: vehicle position relative to the pad in
the heading frame — NED rotated by the current yaw —, ``alt`` above the pad, velocities in the
same frame, attitude and rates from ATTITUDE, specific force from HIGHRES_IMU in g0 units)."""

_G0 = 9.80665


class CheckpointError(ValueError):
    """A checkpoint file is missing, corrupt, of another format, or does not fit its network."""


# ----------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class NetConfig:
    """Everything needed to rebuild the networks and the estimator (stored in checkpoints)."""

    kind: str = "vision"
    """``vision`` (CNN + estimator + LSTM) or ``privileged`` (ground-truth position/velocity)."""
    cnn_channels: tuple[int, ...] = (8, 16, 24, 32)
    cnn_context_layers: int = 0
    """Extra dilated (4) 3x3 convolutions before the heat map: a receptive field that spans the
    image, so a pad larger than the old field (low altitude) is still localised by its cross."""
    lstm_hidden: int = 64
    mlp_hidden: int = 64
    hover_thrust_norm: float = 0.3923
    max_rate_rad_s: tuple[float, float, float] = (3.5, 3.5, 1.5)
    gravity_m_s2: float = 9.80665
    control_dt_s: float = 0.1
    fov_deg: float = CAMERA_FOV_DEG
    image_size_px: int = IMAGE_SIZE_PX
    # PadEstimator noise model (1-sigma)
    accel_noise_m_s2: float = 0.3
    bearing_noise_rad: float = 0.01
    bearing_noise_floor_m: float = 0.03
    alt_noise_m: float = 0.05
    visibility_threshold: float = 0.5
    gate_sigma: float = 4.0
    """Innovation gate of the horizontal fix (Mahalanobis distance, 2 dof); 0 disables it."""
    gate_reset_steps: int = 10
    """After this many consecutive gated fixes the estimator re-acquires from the fix."""
    min_fix_altitude_m: float = 1.5
    """Below this the view is a piece of one cross arm and the bearing is a guess: the
    horizontal estimate flies on the IMU prediction (the radar altitude is still used)."""

    def __post_init__(self) -> None:
        if self.kind not in ("vision", "privileged"):
            raise CheckpointError(
                f"net config kind: expected 'vision' or 'privileged', got {self.kind!r}"
            )
        if not 0.0 < self.hover_thrust_norm < 1.0:
            raise CheckpointError(
                f"net config hover_thrust_norm: expected in (0, 1), got {self.hover_thrust_norm}"
            )
        if len(self.max_rate_rad_s) != 3 or min(self.max_rate_rad_s) <= 0:
            raise CheckpointError(
                f"net config max_rate_rad_s: expected 3 positive values, got {self.max_rate_rad_s}"
            )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["cnn_channels"] = list(self.cnn_channels)
        d["max_rate_rad_s"] = list(self.max_rate_rad_s)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> NetConfig:
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known
        if unknown:
            raise CheckpointError(f"net config: unknown keys {sorted(unknown)}")
        d = dict(d)
        if "cnn_channels" in d:
            d["cnn_channels"] = tuple(int(c) for c in d["cnn_channels"])
        if "max_rate_rad_s" in d:
            d["max_rate_rad_s"] = tuple(float(v) for v in d["max_rate_rad_s"])
        return cls(**d)


# ----------------------------------------------------------------------------- geometry


def rotation_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) rotation body FRD -> NED from ZYX Euler angles (MAVLink ATTITUDE)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def position_from_bearing(
    tan_right: float, tan_forward: float, attitude_rad: np.ndarray, range_m: float
) -> np.ndarray | None:
    """Vehicle position relative to the pad (NED, m) from the pad's bearing in the camera.

    The camera looks along body down with image up = body forward, so a pad seen at
    ``(tan_right, tan_forward)`` lies along body ``(tan_forward, tan_right, 1)``. The radar range
    is along body down, so the altitude is ``range * cos(roll) cos(pitch)``. Returns ``None`` when
    the geometry is degenerate (invalid range, ray not pointing at the ground).
    """
    if not math.isfinite(range_m) or range_m < 0:
        return None
    rot = rotation_zyx(*(float(a) for a in attitude_rad))
    alt = range_m * rot[2, 2]
    ray = rot @ np.array([tan_forward, tan_right, 1.0])
    if ray[2] <= 1e-3 or alt <= 0:
        return None
    to_pad = ray * (alt / ray[2])
    return np.array([-to_pad[0], -to_pad[1], -alt])


def control_features(
    pos_ned_m: np.ndarray,
    vel_ned_m_s: np.ndarray,
    attitude_rad: np.ndarray,
    rate_frd_rad_s: np.ndarray,
    accel_frd_m_s2: np.ndarray,
    visibility: float,
) -> np.ndarray:
    """The controller's input vector (:data:`FEATURE_NAMES`), float32."""
    roll, pitch, yaw = (float(a) for a in attitude_rad)
    c, s = math.cos(yaw), math.sin(yaw)
    x_h = c * pos_ned_m[0] + s * pos_ned_m[1]
    y_h = -s * pos_ned_m[0] + c * pos_ned_m[1]
    vx_h = c * vel_ned_m_s[0] + s * vel_ned_m_s[1]
    vy_h = -s * vel_ned_m_s[0] + c * vel_ned_m_s[1]
    alt = -float(pos_ned_m[2])
    inv = 1.0 / (max(alt, 0.0) + 1.0)
    return np.array(
        [
            x_h / 10,
            y_h / 10,
            alt / 50,
            min(max(alt, 0.0), 5.0) / 5,
            x_h * inv,
            y_h * inv,
            vx_h / 3,
            vy_h / 3,
            float(vel_ned_m_s[2]) / 3,
            roll,
            pitch,
            float(rate_frd_rad_s[0]),
            float(rate_frd_rad_s[1]),
            float(rate_frd_rad_s[2]),
            float(accel_frd_m_s2[0]) / _G0,
            float(accel_frd_m_s2[1]) / _G0,
            float(accel_frd_m_s2[2]) / _G0,
            float(visibility),
        ],
        dtype=np.float32,
    )


# ----------------------------------------------------------------------------- estimator


@dataclass(frozen=True)
class EstimatorState:
    """Kalman state per NED axis: ``x`` (3, 2) = (position, velocity), ``cov`` (3, 2, 2)."""

    x: np.ndarray
    cov: np.ndarray
    initialised: np.ndarray
    """(3,) bool: the axis has had a measurement."""
    rejected: int = 0
    """Consecutive horizontal fixes refused by the innovation gate."""


class PadEstimator:
    """Pad-relative position and velocity from position fixes and the IMU (3 decoupled axes).

    Predict with the NED acceleration ``R f + g`` (specific force from HIGHRES_IMU rotated by
    ATTITUDE), update with the geometric fix; the horizontal fix noise grows with altitude (a
    fixed angular error of the bearing). A missing fix (pad not visible, invalid range) only
    predicts. A horizontal fix further than ``gate_sigma`` (Mahalanobis) from the prediction is
    refused — one confidently wrong CNN answer (a tilted view without the pad) would otherwise
    move the estimate by tens of metres —, and after ``gate_reset_steps`` refusals in a row the
    estimate re-acquires from the fix (the prediction, not the camera, was wrong).
    """

    def __init__(self, cfg: NetConfig) -> None:
        self.cfg = cfg
        dt = cfg.control_dt_s
        self._f = np.array([[1.0, dt], [0.0, 1.0]])
        self._b = np.array([0.5 * dt * dt, dt])
        q = cfg.accel_noise_m_s2**2
        self._q = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt * dt]])

    def initial_state(self) -> EstimatorState:
        return EstimatorState(
            x=np.zeros((3, 2)),
            cov=np.tile(np.eye(2) * 1e6, (3, 1, 1)),
            initialised=np.zeros(3, bool),
        )

    def step(
        self,
        state: EstimatorState,
        fix_ned_m: np.ndarray | None,
        horizontal_fix: bool,
        attitude_rad: np.ndarray,
        accel_frd_m_s2: np.ndarray,
    ) -> EstimatorState:
        """One control period: predict from the last period's acceleration, then update."""
        x, cov, init = state.x.copy(), state.cov.copy(), state.initialised.copy()
        rejected = state.rejected
        rot = rotation_zyx(*(float(a) for a in attitude_rad))
        acc = rot @ np.asarray(accel_frd_m_s2, float) + np.array([0.0, 0.0, self.cfg.gravity_m_s2])
        if not np.all(np.isfinite(acc)):
            acc = np.zeros(3)
        for axis in range(3):
            if init[axis]:
                x[axis] = self._f @ x[axis] + self._b * acc[axis]
                cov[axis] = self._f @ cov[axis] @ self._f.T + self._q
        if fix_ned_m is not None and np.all(np.isfinite(fix_ned_m)):
            alt = max(-float(fix_ned_m[2]), 0.0)
            sigma_h = self.cfg.bearing_noise_floor_m + self.cfg.bearing_noise_rad * alt
            sigmas = (sigma_h, sigma_h, self.cfg.alt_noise_m)
            horizontal_fix = horizontal_fix and alt >= self.cfg.min_fix_altitude_m
            axes = (0, 1, 2) if horizontal_fix else (2,)
            if horizontal_fix and self.cfg.gate_sigma > 0 and init[0] and init[1]:
                d2 = sum(
                    (float(fix_ned_m[a]) - x[a, 0]) ** 2 / (cov[a, 0, 0] + sigma_h**2)
                    for a in (0, 1)
                )
                if d2 > self.cfg.gate_sigma**2:
                    rejected += 1
                    if rejected >= self.cfg.gate_reset_steps:
                        init[:2] = False  # re-acquire below from this fix
                        rejected = 0
                    else:
                        axes = (2,)
                else:
                    rejected = 0
            for axis in axes:
                z = float(fix_ned_m[axis])
                if not init[axis]:
                    x[axis] = (z, 0.0)
                    cov[axis] = np.diag([sigmas[axis] ** 2, 4.0])
                    init[axis] = True
                    continue
                p = cov[axis]
                s = p[0, 0] + sigmas[axis] ** 2
                k = p[:, 0] / s
                x[axis] = x[axis] + k * (z - x[axis, 0])
                cov[axis] = p - np.outer(k, p[0, :])
        return EstimatorState(x=x, cov=cov, initialised=init, rejected=rejected)


# ----------------------------------------------------------------------------- networks


class PerceptionCNN(nn.Module):
    """Image -> (tan_right, tan_forward, visibility logit) of the pad centre.

    Four strided/dilated 3x3 convolutions to a 16x16 heat map, soft-argmax over the map gives the
    expected pixel of the pad centre (sub-cell precision, translation-equivariant), converted to a
    bearing with the pinhole model; visibility from the pooled features and the map's peak.
    """

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        c1, c2, c3, c4 = cfg.cnn_channels
        self.features = nn.Sequential(
            nn.Conv2d(1, c1, 5, stride=2, padding=2),
            nn.ReLU(inplace=True),
            nn.Conv2d(c1, c2, 3, stride=2, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(c2, c3, 3, stride=2, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(c3, c4, 3, stride=1, padding=2, dilation=2),
            nn.ReLU(inplace=True),
            *(
                m
                for _ in range(cfg.cnn_context_layers)
                for m in (nn.Conv2d(c4, c4, 3, stride=1, padding=4, dilation=4), nn.ReLU(True))
            ),
        )
        self.heat = nn.Conv2d(c4, 1, 1)
        self.visibility = nn.Linear(c4 + 1, 1)
        self.bias = nn.Parameter(torch.zeros(2))
        size = cfg.image_size_px
        cells = size // 8
        focal = 0.5 * size / math.tan(math.radians(cfg.fov_deg) / 2)
        centres = (torch.arange(cells, dtype=torch.float32) + 0.5) * (size / cells)
        self.register_buffer("tan_cols", (centres - size / 2) / focal, persistent=False)
        self.register_buffer("tan_rows", (size / 2 - centres) / focal, persistent=False)

    def forward(self, image_u8: torch.Tensor) -> torch.Tensor:
        """``image_u8``: (B, H, W) or (B, 1, H, W), uint8 or float in [0, 255]. Returns (B, 3)."""
        x = image_u8
        if x.dim() == 3:
            x = x.unsqueeze(1)
        x = x.float() * (1.0 / 255.0) - 0.5
        f = self.features(x)
        logits = self.heat(f).flatten(1)  # (B, cells*cells)
        prob = torch.softmax(logits, dim=1)
        cells = self.tan_cols.numel()
        prob = prob.view(-1, cells, cells)
        tan_right = (prob.sum(dim=1) * self.tan_cols).sum(dim=1)
        tan_forward = (prob.sum(dim=2) * self.tan_rows).sum(dim=1)
        pooled = f.mean(dim=(2, 3))
        peak = logits.max(dim=1, keepdim=True).values
        vis = self.visibility(torch.cat([pooled, peak], dim=1)).squeeze(1)
        return torch.stack([tan_right + self.bias[0], tan_forward + self.bias[1], vis], dim=1)


class ControlLSTM(nn.Module):
    """Features -> Command with explicit LSTM state; outputs always inside the Command ranges.

    ``thrust_norm = sigmoid(z0 + logit(hover))`` (zero output = hover) and
    ``rates = max_rate * tanh(z)``.
    """

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        n_in = len(FEATURE_NAMES)
        self.encoder = nn.Sequential(nn.Linear(n_in, cfg.mlp_hidden), nn.Tanh())
        self.lstm = nn.LSTM(cfg.mlp_hidden, cfg.lstm_hidden, batch_first=True)
        self.head = nn.Sequential(
            nn.Linear(cfg.lstm_hidden + cfg.mlp_hidden, cfg.mlp_hidden),
            nn.Tanh(),
            nn.Linear(cfg.mlp_hidden, 4),
        )
        self.hidden = cfg.lstm_hidden
        self.register_buffer(
            "hover_logit",
            torch.tensor(math.log(cfg.hover_thrust_norm / (1 - cfg.hover_thrust_norm))),
            persistent=False,
        )
        self.register_buffer(
            "max_rate", torch.tensor(cfg.max_rate_rad_s, dtype=torch.float32), persistent=False
        )

    def zero_state(self, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        z = torch.zeros(1, batch, self.hidden)
        return z, z.clone()

    def forward(
        self, features: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """``features`` (B, T, F) -> commands (B, T, 4) = (thrust_norm, p, q, r), next state."""
        e = self.encoder(features)
        if state is None:
            state = self.zero_state(features.shape[0])
        h, state = self.lstm(e, state)
        z = self.head(torch.cat([h, e], dim=-1))
        thrust = torch.sigmoid(z[..., :1] + self.hover_logit)
        rates = self.max_rate * torch.tanh(z[..., 1:])
        return torch.cat([thrust, rates], dim=-1), state


# ----------------------------------------------------------------------------- the policy


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

    ``groundtruth`` is read only by privileged policies, duck-typed (any object with numpy
    ``pos_ned_m`` and ``vel_ned_m_s``), so the simulator's GroundTruth and the companion's
    ODOMETRY record both fit. Vision policies ignore it (pass ``None`` on hardware).
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


# ----------------------------------------------------------------------------- checkpoints


def save_checkpoint(
    path: str | Path,
    config: NetConfig,
    control: ControlLSTM,
    perception: PerceptionCNN | None,
    metadata: dict[str, Any],
) -> Path:
    """Write a checkpoint atomically (``.tmp`` then rename). ``metadata``: JSON-able values."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "net_config": config.to_dict(),
        "feature_names": list(FEATURE_NAMES),
        "control": control.state_dict(),
        "perception": perception.state_dict() if perception is not None else None,
        "metadata": metadata,
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(blob, tmp)
    tmp.replace(path)
    return path


def _load_blob(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a damaged zip/pickle
        raise CheckpointError(
            f"{path}: not a readable visland checkpoint ({type(exc).__name__}: {exc})"
        ) from None
    if not isinstance(blob, dict) or blob.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"{path}: not a visland policy checkpoint (expected format {CHECKPOINT_FORMAT!r})"
        )
    if blob.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint version {blob.get('version')!r}, this code reads "
            f"{CHECKPOINT_VERSION}"
        )
    if list(blob.get("feature_names", [])) != list(FEATURE_NAMES):
        raise CheckpointError(f"{path}: feature_names differ from this code's controller inputs")
    return blob


def load_networks(path: str | Path) -> tuple[NetConfig, ControlLSTM, PerceptionCNN | None, dict]:
    """The checkpoint's config and networks (for training to continue from)."""
    path = Path(path)
    blob = _load_blob(path)
    try:
        cfg = NetConfig.from_dict(dict(blob["net_config"]))
    except (TypeError, KeyError) as exc:
        raise CheckpointError(f"{path}: net_config: {exc}") from None
    except CheckpointError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    control = ControlLSTM(cfg)
    perception = PerceptionCNN(cfg) if blob.get("perception") is not None else None
    try:
        control.load_state_dict(blob["control"])
        if perception is not None:
            perception.load_state_dict(blob["perception"])
    except (RuntimeError, KeyError, TypeError) as exc:
        raise CheckpointError(f"{path}: weights do not fit the network: {exc}") from None
    for name, module in (("control", control), ("perception", perception)):
        if module is None:
            continue
        for pname, p in module.state_dict().items():
            if not torch.all(torch.isfinite(p)):
                raise CheckpointError(f"{path}: {name}.{pname} holds non-finite values")
    return cfg, control, perception, dict(blob.get("metadata") or {})


def load_policy(path: str | Path) -> LearnedPolicy:
    """Load a checkpoint as a ready-to-fly policy. Raises :class:`CheckpointError`."""
    cfg, control, perception, meta = load_networks(path)
    if cfg.kind == "vision" and perception is None:
        raise CheckpointError(f"{path}: vision policy without perception weights")
    return LearnedPolicy(cfg, control, perception if cfg.kind == "vision" else None, meta)


def untrained_policy(seed: int = 0, privileged: bool = False) -> LearnedPolicy:
    """A randomly initialised policy of the shipped size (for tests and latency benchmarks)."""
    torch.manual_seed(seed)
    cfg = NetConfig(kind="privileged" if privileged else "vision")
    return LearnedPolicy(
        cfg, ControlLSTM(cfg), None if privileged else PerceptionCNN(cfg), {"untrained": True}
    )
