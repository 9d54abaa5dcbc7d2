"""Training steps: controller behaviour cloning from the replay buffer, perception regression.

Both run on the CPU with a seeded generator (same seed, same data => same weights on one
machine) and report through a ``log(name, value, step)`` callback (TensorBoard / console).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from companion.policy_net import (
    FEATURE_NAMES,
    ControlLSTM,
    LearnedPolicy,
    NetConfig,
    PerceptionCNN,
    control_features,
)
from sitl_sim.config import Planet, SimConfig, VehicleConfig
from sitl_sim.physics.dynamics import quat_to_rotation
from training.dataset import Episode
from training.replay import BufferedEpisode, ReplayBuffer

__all__ = [
    "COMMAND_SCALE",
    "ControllerFit",
    "LabelGate",
    "PerceptionFit",
    "bearing_labels",
    "net_config_for",
    "privileged_episode",
    "train_controller",
    "train_perception",
    "vision_episode",
]

COMMAND_SCALE = np.array([0.05, 0.25, 0.25, 0.25], dtype=np.float32)
_NEAR_GROUND = FEATURE_NAMES.index("min(alt,5)/5")
"""Loss scale per command component (thrust_norm, p, q, r): errors are measured in these units.
(A smaller thrust scale starves the rates of gradient: the policy then steers badly.)"""

Logger = Callable[[str, float, int], None]


def _no_log(name: str, value: float, step: int) -> None:
    return None


def net_config_for(
    vehicle: VehicleConfig,
    sim: SimConfig,
    kind: str,
    planet: Planet | None = None,
    **options: bool | float | None,
) -> NetConfig:
    """The network config matching a vehicle and world (hover thrust, rate limits, gravity),
    with the profile's options (``Profile.net_options``: robustness switches and estimator
    settings, :class:`NetConfig` fields by name; the defaults are the paper-world model's)."""
    planet = planet or sim.planet
    g = planet.gravity_m_s2
    return NetConfig(
        **options,
        kind=kind,
        hover_thrust_norm=vehicle.hover_thrust_norm(planet),
        max_rate_rad_s=tuple(float(v) for v in vehicle.rate_controller.max_rate_rad_s),
        gravity_m_s2=g,
        control_dt_s=1.0 / sim.control_rate_hz,
        fov_deg=sim.camera.fov_deg,
        image_size_px=sim.camera.height_px,
        cnn_context_layers=1,
    )


# ----------------------------------------------------------------------------- features


def _per_step(ep: Episode, key: str) -> np.ndarray:
    """An optional per-step array of ``ep``, NaN where the episode has none."""
    arr = getattr(ep, key)
    return np.full(len(ep), math.nan) if arr is None else arr


def privileged_episode(ep: Episode, cfg: NetConfig | None = None) -> BufferedEpisode:
    """Controller inputs from ground-truth position/velocity (the privileged variant).

    ``cfg``: the config of the controller to feed (its ``hover_input``); None: without it.
    """
    hover = _per_step(ep, "hover_thrust_norm")
    feats = np.stack(
        [
            control_features(
                ep.pos_ned_m[t],
                ep.vel_ned_m_s[t],
                ep.attitude_rad[t],
                ep.rate_frd_rad_s[t],
                ep.accel_frd_m_s2[t],
                1.0,
                None if cfg is None else cfg.hover_feature(float(hover[t])),
            )
            for t in range(len(ep))
        ]
    )
    return BufferedEpisode(ep.name, feats, ep.label.astype(np.float32))


@dataclass(frozen=True)
class LabelGate:
    """Which steps of a flight a vision controller learns its label at: those where the
    estimate it flies by (CNN + estimator, as replayed) has the pad, within
    ``max(floor_m, fraction * altitude)`` of the truth (3-D).

    Elsewhere the expert's label — computed from the true state — answers a question the
    learner cannot ask: a learner that lost the pad, or never saw it, is hundreds of metres
    off and the label there is a saturated dash to a pad it does not know of. Such steps are
    a minority of the steps and most of the loss (a robust run's first vision round: 80–97 %
    of it in the worlds where the learner loses the pad), and a controller fit to them flies
    worse than the one it started from. They still feed the LSTM's state (weight 0, not cut
    out), so the steps after a recovery are learnt with the memory they had."""

    fraction: float = 0.1
    floor_m: float = 2.0
    velocity_m_s: float = 1.0
    """... and whose velocity relative to the pad is within this of the truth (a pad that
    moves under an estimate that takes it as still: the label chases a motion the learner
    does not know of)."""

    def weights(
        self,
        estimate_ned_m: np.ndarray,
        truth_ned_m: np.ndarray,
        estimate_vel_ned_m_s: np.ndarray,
        truth_vel_ned_m_s: np.ndarray,
    ) -> np.ndarray:
        """(T,) 1.0 where the estimate (T, 3 position and velocity; NaN: none yet) is within
        the gate, else 0.0."""
        alt = np.maximum(-truth_ned_m[:, 2], 0.0)
        err = np.linalg.norm(estimate_ned_m - truth_ned_m, axis=1)
        verr = np.linalg.norm(estimate_vel_ned_m_s - truth_vel_ned_m_s, axis=1)
        ok = (err <= np.maximum(self.floor_m, self.fraction * alt)) & (verr <= self.velocity_m_s)
        return ok.astype(np.float32)


def vision_episode(
    policy: LearnedPolicy, ep: Episode, gate: LabelGate | None = None
) -> BufferedEpisode:
    """Controller inputs as the vision policy computes them in flight (CNN + estimator).

    The CNN runs batched over the recorded frames; the estimator and feature code are the
    policy's own (``LearnedPolicy.vision_features``), step by step. ``gate``: the steps'
    loss weights from the replayed estimate against the logged truth (:class:`LabelGate`);
    None: every step learnt.
    """
    if ep.images is None:
        raise ValueError(f"{ep.name}: vision features need the camera frames")
    assert policy.perception is not None
    with torch.inference_mode():
        raw = np.concatenate(
            [
                policy.perception(torch.from_numpy(np.array(ep.images[i : i + 256]))).numpy()
                for i in range(0, len(ep), 256)
            ]
        ).astype(float)
    state = policy.initial_state()
    feats = []
    hover = _per_step(ep, "hover_thrust_norm")
    image_t = _per_step(ep, "image_time_s")
    attitude_t = _per_step(ep, "attitude_time_s")
    range_t = _per_step(ep, "range_time_s")
    estimate = np.full((len(ep), 2, 3), math.nan)
    for t in range(len(ep)):
        f, state = policy.vision_features(
            raw[t],
            ep.attitude_rad[t],
            ep.rate_frd_rad_s[t],
            ep.accel_frd_m_s2[t],
            float(ep.range_m[t]),
            state,
            hover_thrust_norm=float(hover[t]),
            image_time_s=float(image_t[t]),
            attitude_time_s=float(attitude_t[t]),
            range_time_s=float(range_t[t]),
        )
        feats.append(f)
        est = state.estimator
        if est is not None and bool(np.all(est.initialised)):
            estimate[t] = est.x[:, :2].T
    weights = (
        None
        if gate is None
        else gate.weights(estimate[:, 0], ep.pos_ned_m, estimate[:, 1], ep.vel_ned_m_s)
    )
    return BufferedEpisode(ep.name, np.stack(feats), ep.label.astype(np.float32), weights)


# ----------------------------------------------------------------------------- controller


@dataclass(frozen=True)
class ControllerFit:
    steps: int
    final_loss: float
    seconds: float


def train_controller(
    control: ControlLSTM,
    buffer: ReplayBuffer,
    steps: int,
    batch_segments: int = 32,
    lr: float = 1e-3,
    seed: int = 0,
    burn_in_steps: int = 0,
    ground_weight: float = 4.0,
    log: Logger = _no_log,
    log_prefix: str = "controller",
    step_offset: int = 0,
    progress: Callable[[int], None] | None = None,
) -> ControllerFit:
    """Behaviour cloning on buffer segments (paper 4.2), each after ``burn_in_steps`` of
    state warm-up from the same episode (no loss there; see ``ReplayBuffer.sample``).
    Steps below 5 m weigh up to ``1 + ground_weight`` (linear in altitude): the flare to the
    expert's 0.17 m/s touchdown is a few percent of the data but decides success.

    Loss: mean squared command error in :data:`COMMAND_SCALE` units; Adam with a cosine decay
    to 10 % of ``lr``; gradient norm clipped at 1.
    """
    torch.manual_seed(seed)
    control.train()
    opt = torch.optim.Adam(control.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(s / max(steps, 1), 1.0)))
    )
    scale = torch.from_numpy(COMMAND_SCALE)
    t0 = time.perf_counter()
    running = math.nan
    for step in range(steps):
        feats, labels, mask = buffer.sample(batch_segments, burn_in_steps)
        pred, _ = control(torch.from_numpy(feats))
        err = (((pred - torch.from_numpy(labels)) / scale) ** 2).mean(dim=-1)
        x = torch.from_numpy(feats)
        m = torch.from_numpy(mask) * (1.0 + ground_weight * (1.0 - x[..., _NEAR_GROUND]))
        loss = (err * m).sum() / m.sum().clamp_min(1e-6)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(control.parameters(), 1.0)
        opt.step()
        sched.step()
        value = float(loss.detach())
        if not math.isfinite(value):
            raise FloatingPointError(f"{log_prefix}: loss became {value} at step {step}")
        running = value if math.isnan(running) else 0.98 * running + 0.02 * value
        if step % 50 == 0 or step == steps - 1:
            log(f"{log_prefix}/loss", running, step_offset + step)
        if progress is not None:
            progress(1)
    control.eval()
    return ControllerFit(steps, running, time.perf_counter() - t0)


# ----------------------------------------------------------------------------- perception


def bearing_labels(pos_ned_m: np.ndarray, quat_wxyz: np.ndarray, fov_deg: float) -> np.ndarray:
    """(N, 3): the pad centre's (tan_right, tan_forward) in the camera and visible (0/1).

    Computed from ground truth: the pad centre is the NED origin, the camera looks along body
    down with image up = body forward.
    """
    out = np.zeros((pos_ned_m.shape[0], 3), dtype=np.float32)
    half = math.tan(math.radians(fov_deg) / 2)
    for i in range(pos_ned_m.shape[0]):
        rel_body = quat_to_rotation(quat_wxyz[i]).T @ (-pos_ned_m[i])
        if rel_body[2] <= 1e-6:
            continue
        tr, tf = rel_body[1] / rel_body[2], rel_body[0] / rel_body[2]
        out[i] = (tr, tf, float(abs(tr) < half and abs(tf) < half))
    return out


def _shift(
    img: torch.Tensor,
    y: torch.Tensor,
    rng: np.random.Generator,
    max_shift: int,
    focal: float,
    half_fov: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Translate each image by a random whole-pixel (dx right, dy down); edges replicated."""
    n, h, w = img.shape
    padded = nn.functional.pad(img[:, None], (max_shift,) * 4, mode="replicate")[:, 0]
    shifts = rng.integers(-max_shift, max_shift + 1, size=(n, 2))
    out = torch.empty_like(img)
    for i, (dx, dy) in enumerate(shifts):
        top, left = max_shift - int(dy), max_shift - int(dx)
        out[i] = padded[i, top : top + h, left : left + w]
    y = y.clone()
    y[:, 0] += torch.from_numpy(shifts[:, 0] / focal).float()
    y[:, 1] -= torch.from_numpy(shifts[:, 1] / focal).float()
    inside = (y[:, 0].abs() < half_fov) & (y[:, 1].abs() < half_fov)
    y[:, 2] = y[:, 2] * inside.float()
    return out, y


@dataclass(frozen=True)
class PerceptionFit:
    epochs: int
    train_images: int
    val_images: int
    val_bearing_error_px_median: float
    val_bearing_error_px_p95: float
    val_position_error_m_median: float
    val_position_error_m_p95: float
    val_visibility_accuracy: float
    seconds: float
    pose_images: int = 0
    pose_val_bearing_error_px_median: float = math.nan
    pose_val_bearing_error_px_p95: float = math.nan
    pose_val_visibility_accuracy: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _split(n_episodes: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    order = np.random.default_rng(seed).permutation(n_episodes)
    n_val = max(1, round(n_episodes * val_fraction)) if n_episodes > 1 else 0
    return order[n_val:], order[:n_val]


def train_perception(
    cnn: PerceptionCNN,
    episodes: list[Episode],
    epochs: int,
    batch: int = 64,
    lr: float = 2e-3,
    seed: int = 0,
    frame_stride: int = 2,
    val_fraction: float = 0.1,
    max_shift_px: int = 40,
    log: Logger = _no_log,
    progress: Callable[[int], None] | None = None,
    extra: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    gain: tuple[float, float] = (0.8, 1.2),
    held: tuple[np.ndarray, np.ndarray] | None = None,
) -> PerceptionFit:
    """Regress the pad bearing (+ visibility) from expert-flight frames, split 90/10 by episode.

    Loss: Huber on the bearing in pixels (only where the pad centre is in view) + binary
    cross-entropy on visibility. Augmentation: a random gain (uniform in ``gain``) and offset of
    the grey levels (a camera's exposure: a low sun darkens the whole frame) and random image
    translations of up to ``max_shift_px`` (the bearing label moves by exactly ``shift /
    focal``): the expert keeps the pad near the image centre, and without shifts the CNN learns
    to answer "centre" whatever it sees.

    ``extra``: more frames ``(images, pos_ned_m, quat_wxyz)`` (e.g. the pose-sampled renders of
    :mod:`training.perception_data`), labelled the same way and split 90/10 by index; their
    validation figures are reported separately (``pose_val_*``). With ``extra``, ``episodes`` may
    be empty (a CNN taught a new pad from rendered frames alone: ``val_*`` are then NaN).

    ``held``: training frames with given labels ``(images, (N, 3) tan_right, tan_forward,
    pad probability)``, e.g. a source CNN's own outputs that a fine-tune must keep.
    """
    if any(e.images is None for e in episodes):
        raise ValueError("perception training needs episodes with camera frames")
    if not 0.0 < gain[0] <= gain[1]:
        raise ValueError(f"gain = {gain}; expected (lo, hi) with 0 < lo <= hi")
    if not episodes and (extra is None or not len(extra[0])):
        raise ValueError("perception training needs episodes with camera frames or extra frames")
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    focal = float(0.5 * 128 / math.tan(math.radians(45.0) / 2))
    half_fov = math.tan(math.radians(45.0) / 2)
    tr_idx, va_idx = _split(len(episodes), val_fraction, seed)

    def gather(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        imgs, labs, alts = [], [], []
        for k in idx:
            e = episodes[int(k)]
            sel = np.arange(0, len(e), frame_stride)
            imgs.append(e.images[sel])
            labs.append(bearing_labels(e.pos_ned_m[sel], e.quat_wxyz[sel], 45.0))
            alts.append(-e.pos_ned_m[sel, 2])
        if not imgs:
            return (np.zeros((0, 128, 128), np.uint8), np.zeros((0, 3), np.float32), np.zeros(0))
        return np.concatenate(imgs), np.concatenate(labs), np.concatenate(alts)

    x_tr, y_tr, _ = gather(tr_idx)
    x_va, y_va, alt_va = gather(va_idx)
    x_pv = np.zeros((0, 128, 128), np.uint8)
    y_pv = np.zeros((0, 3), np.float32)
    alt_pv = np.zeros(0)
    if extra is not None and len(extra[0]):
        images, pos, quat = extra
        labels = bearing_labels(pos, quat, 45.0)
        order = rng.permutation(len(images))
        n_pv = max(1, round(len(images) * val_fraction))
        pv, pt = np.sort(order[:n_pv]), np.sort(order[n_pv:])
        x_tr = np.concatenate([x_tr, images[pt]])
        y_tr = np.concatenate([y_tr, labels[pt]])
        x_pv, y_pv, alt_pv = images[pv], labels[pv], -pos[pv, 2]
    if held is not None and len(held[0]):
        x_tr = np.concatenate([x_tr, held[0]])
        y_tr = np.concatenate([y_tr, np.asarray(held[1], np.float32)])
    opt = torch.optim.Adam(cnn.parameters(), lr=lr)
    n = x_tr.shape[0]
    steps_total = epochs * max(1, n // batch)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(s / steps_total, 1.0)))
    )
    bce = nn.BCEWithLogitsLoss()
    t0 = time.perf_counter()
    step = 0
    for epoch in range(epochs):
        cnn.train()
        order = rng.permutation(n)
        for b in range(max(1, n // batch)):
            sel = order[b * batch : (b + 1) * batch]
            img = torch.from_numpy(x_tr[sel]).float()
            g = torch.from_numpy(rng.uniform(*gain, (len(sel), 1, 1)).astype(np.float32))
            offset = torch.from_numpy(rng.uniform(-20, 20, (len(sel), 1, 1)).astype(np.float32))
            img = (img * g + offset).clamp(0, 255)
            y = torch.from_numpy(y_tr[sel].copy())
            if max_shift_px > 0:
                img, y = _shift(img, y, rng, max_shift_px, focal, half_fov)
            out = cnn(img)
            vis = y[:, 2]
            err_px = (out[:, :2] - y[:, :2]) * focal
            huber = nn.functional.smooth_l1_loss(err_px, torch.zeros_like(err_px), reduction="none")
            loss_b = (huber.sum(dim=1) * vis).sum() / vis.sum().clamp(min=1.0)
            loss = loss_b + bce(out[:, 2], vis)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            if step % 50 == 0:
                log("perception/loss", float(loss.detach()), step)
            step += 1
            if progress is not None:
                progress(1)
        log("perception/epoch", float(epoch), step)
    cnn.eval()
    med_px, p95_px, med_m, p95_m, acc = _perception_errors(cnn, x_va, y_va, alt_va, focal)
    log("perception/val_bearing_error_px_median", med_px, step)
    pose = _perception_errors(cnn, x_pv, y_pv, alt_pv, focal)
    return PerceptionFit(
        epochs=epochs,
        train_images=int(n),
        val_images=int(x_va.shape[0]),
        val_bearing_error_px_median=med_px,
        val_bearing_error_px_p95=p95_px,
        val_position_error_m_median=med_m,
        val_position_error_m_p95=p95_m,
        val_visibility_accuracy=acc,
        seconds=time.perf_counter() - t0,
        pose_images=len(extra[0]) if extra is not None else 0,
        pose_val_bearing_error_px_median=pose[0],
        pose_val_bearing_error_px_p95=pose[1],
        pose_val_visibility_accuracy=pose[4],
    )


def _perception_errors(
    cnn: PerceptionCNN, x: np.ndarray, y: np.ndarray, alt: np.ndarray, focal: float
) -> tuple[float, float, float, float, float]:
    """Bearing error median/p95 (px, where visible), position error median/p95 (m), visibility
    accuracy of ``cnn`` on labelled frames (NaN when there are none)."""
    med_px = p95_px = med_m = p95_m = acc = math.nan
    if x.shape[0] == 0:
        return med_px, p95_px, med_m, p95_m, acc
    with torch.inference_mode():
        out = torch.cat([cnn(torch.from_numpy(x[i : i + 256])) for i in range(0, len(x), 256)])
    out = out.numpy()
    vis = y[:, 2] > 0.5
    err = np.linalg.norm(out[:, :2] - y[:, :2], axis=1)
    if vis.any():
        med_px, p95_px = (float(np.percentile(err[vis] * focal, q)) for q in (50, 95))
        err_m = err[vis] * alt[vis]
        med_m, p95_m = (float(np.percentile(err_m, q)) for q in (50, 95))
    acc = float(np.mean((out[:, 2] > 0) == vis))
    return med_px, p95_px, med_m, p95_m, acc
