"""``visland pad error``: where a checkpoint's CNN places the pad, per scenario and altitude band.

The figures behind every "the CNN answers a metre towards the rover's cab" in the docs, as a
command. For each scenario (its ``[visual]``, ``[pad]`` and ``[terrain]`` sections) and each
altitude band it renders nearly level frames with the pad in view through the simulator's own
camera (:func:`training.perception_data.render_pose_frames`, one drawn look, pad and site per
``chunk`` frames, all bands on the same draws), runs the CNN on them and reports:

- ``seen`` / ``acquired``: the share of frames at or above the checkpoint's
  ``visibility_threshold`` (a fix; landing-target mode streams only then) and
  ``acquire_threshold`` (a fix that may start the estimate);
- the error of the predicted bearing turned into metres at the frame's height, its median and
  90th percentile, and in pixels of the net's image;
- its median along the pad's own axes (``forward``: the carrier's nose on a rover or a deck,
  north for a still pad on flat ground; ``right``): a constant offset there is a bias, not noise;
- ``false_seen`` / ``false_acquired``: the same shares on as many frames of the scenario's ground
  with no pad in them (the camera 40–300 m from it, ``PoseSampling.away_fraction``): a CNN that
  finds pads in bare ground sends the vehicle down onto it.

Seed 500 is the validation seed; a CNN's training frames are drawn from the run's seed + 7.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np

__all__ = ["ErrorConfig", "cnn_error", "format_error", "parse_band"]

BANDS_M: tuple[tuple[float, float], ...] = ((1.0, 8.0), (8.0, 20.0), (20.0, 40.0), (40.0, 100.0))
"""The default altitude bands (m): the last metres, the final approach, mid, the start."""


@dataclass(frozen=True)
class ErrorConfig:
    """What ``visland pad error`` measures (its flags)."""

    checkpoint: Path | None = None
    """A vision policy checkpoint; None: the shipped model."""
    scenarios: tuple[Path, ...] = (Path("configs/scenario.toml"),)
    bands_m: tuple[tuple[float, float], ...] = BANDS_M
    frames: int = 256
    """Frames per scenario and band."""
    seed: int = 500
    chunk: int = 32
    """Frames per drawn look (ground, light, pad, site)."""
    max_tilt_deg: float = 8.0
    """Roll and pitch uniform in ± this (a level hover or descent)."""
    workers: int = 1


def _check_band(lo: float, hi: float, text: str) -> None:
    if not 0.5 <= lo < hi <= 500.0:  # (NaN fails too)
        raise ValueError(f"band {text!r}: expected LO-HI in metres, 0.5 <= LO < HI <= 500")


def parse_band(text: str) -> tuple[float, float]:
    """``"LO-HI"`` (metres) as a band; a clear error otherwise."""
    lo, sep, hi = text.partition("-")
    try:
        band = (float(lo), float(hi)) if sep else (math.nan, math.nan)
    except ValueError:
        band = (math.nan, math.nan)
    _check_band(*band, text)
    return band


def _probability(cnn: Any, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The CNN's outputs (N, 3) and its visibility probability (N,) on ``images``."""
    import torch

    with torch.no_grad():
        out = cnn(torch.as_tensor(images)).numpy().astype(float)
    return out, 1.0 / (1.0 + np.exp(-out[:, 2]))


def _band_row(
    cnn: Any,
    images: np.ndarray,
    pos: np.ndarray,
    quat: np.ndarray,
    pad_frames: np.ndarray,
    fov_deg: float,
    thresholds: tuple[float, float],
) -> dict[str, Any]:
    """One band's figures from its frames, poses (relative to the pad) and each frame's
    R_pad_to_ned."""
    from sitl_sim.physics.dynamics import quat_to_rotation
    from training.train import bearing_labels

    out, prob = _probability(cnn, images)
    labels = bearing_labels(pos, quat, fov_deg)
    inside = labels[:, 2] >= 0.5
    height = -pos[:, 2]
    d_tan = out[:, :2] - labels[:, :2]  # (right, forward)
    errors = []  # (forward, right) in the pad's axes, metres
    for i in np.flatnonzero(inside):
        body = np.array([d_tan[i, 1], d_tan[i, 0], 0.0]) * height[i]
        errors.append((pad_frames[i].T @ (quat_to_rotation(quat[i]) @ body))[:2])
    e = np.asarray(errors, float).reshape(-1, 2)
    size = e.shape[0]
    norm = np.hypot(e[:, 0], e[:, 1])
    focal_px = (images.shape[-1] / 2) / math.tan(math.radians(fov_deg) / 2)
    px = np.hypot(d_tan[inside, 0], d_tan[inside, 1]) * focal_px

    def stat(values: np.ndarray, q: float) -> float:
        return float(np.percentile(values, q)) if size else math.nan

    return {
        "frames": len(images),
        "in_view": int(size),
        "seen": float(np.mean(prob[inside] >= thresholds[0])) if size else math.nan,
        "acquired": float(np.mean(prob[inside] >= thresholds[1])) if size else math.nan,
        "error_m_median": stat(norm, 50),
        "error_m_p90": stat(norm, 90),
        "error_px_median": stat(px, 50),
        "forward_m_median": stat(e[:, 0], 50),
        "right_m_median": stat(e[:, 1], 50),
    }


def cnn_error(cfg: ErrorConfig) -> dict[str, Any]:
    """The figures of the module docstring: ``{"checkpoint", "seed", "thresholds",
    "scenarios": [{"scenario", "bands": [{"band_m", ...row}]}]}``.

    Raises:
        ConfigError: a bad scenario file; CheckpointError: a bad or privileged checkpoint;
        ValueError: a bad band, frame count or chunk.
    """

    from companion.packaged import shipped_policy
    from companion.policy_net import CheckpointError, load_networks
    from sitl_sim.config import load_sim
    from sitl_sim.scenario import load_scenario
    from training.perception_data import PoseSampling, chunk_pad_frame, render_pose_frames

    if cfg.frames < 1 or cfg.chunk < 1:
        raise ValueError(f"frames = {cfg.frames}, chunk = {cfg.chunk}; expected both >= 1")
    for lo, hi in cfg.bands_m:
        _check_band(lo, hi, f"{lo}-{hi}")
    ckpt = Path(cfg.checkpoint) if cfg.checkpoint is not None else shipped_policy()
    net_cfg, _, cnn, _ = load_networks(ckpt)
    if cnn is None:
        raise CheckpointError(f"{ckpt}: a privileged policy has no CNN; give a vision checkpoint")
    cnn.eval()
    thresholds = (
        float(net_cfg.visibility_threshold),
        float(
            net_cfg.acquire_threshold
            if net_cfg.acquire_threshold is not None
            else net_cfg.visibility_threshold
        ),
    )
    camera = load_sim().camera
    level = PoseSampling(
        in_view_fraction=1.0,
        level_fraction=1.0,
        level_tilt_deg=cfg.max_tilt_deg,
    )
    scenarios = []
    for path in cfg.scenarios:
        sc = load_scenario(path)
        sections = (sc.visual, sc.pad, sc.terrain)
        n_chunks = -(-cfg.frames // cfg.chunk)
        frames_of = np.repeat(
            np.stack([chunk_pad_frame(cfg.seed, k, *sections) for k in range(n_chunks)]),
            cfg.chunk,
            axis=0,
        )[: cfg.frames]
        bands = []
        for lo, hi in cfg.bands_m:
            images, pos, quat = render_pose_frames(
                cfg.frames,
                cfg.seed,
                camera,
                workers=cfg.workers,
                sampling=replace(level, altitude_m=(lo, hi)),
                visuals=(sc.visual,),
                pads=(sc.pad,),
                terrains=(sc.terrain,),
                chunk=cfg.chunk,
            )
            row = _band_row(cnn, images, pos, quat, frames_of, camera.fov_deg, thresholds)
            bare, _, _ = render_pose_frames(
                cfg.frames,
                cfg.seed + 1,
                camera,
                workers=cfg.workers,
                sampling=replace(level, altitude_m=(lo, hi), away_fraction=1.0),
                visuals=(sc.visual,),
                pads=(sc.pad,),
                terrains=(sc.terrain,),
                chunk=cfg.chunk,
            )
            prob = _probability(cnn, bare)[1]
            row["false_seen"] = float(np.mean(prob >= thresholds[0]))
            row["false_acquired"] = float(np.mean(prob >= thresholds[1]))
            bands.append({"band_m": [lo, hi], **row})
        scenarios.append({"scenario": str(path), "bands": bands})
    return {
        "checkpoint": str(ckpt),
        "seed": cfg.seed,
        "frames_per_band": cfg.frames,
        "thresholds": {"seen": thresholds[0], "acquired": thresholds[1]},
        "scenarios": scenarios,
    }


def format_error(res: dict[str, Any], out: TextIO) -> None:
    """The figures as one table per scenario."""
    th = res["thresholds"]
    print(
        f"CNN of {res['checkpoint']}: seed {res['seed']}, {res['frames_per_band']} level frames "
        f"per band; seen = p >= {th['seen']:.2f}, acquired = p >= {th['acquired']:.2f}; "
        "error in metres at the frame's height, forward/right along the pad's axes; false: the "
        "same shares on frames of the ground with no pad in them",
        file=out,
    )
    head = (
        f"  {'band (m)':>10} {'seen':>6} {'acq':>6} {'|e| med':>8} {'|e| p90':>8} "
        f"{'px med':>7} {'fwd med':>8} {'right med':>9} {'false seen':>10} {'false acq':>9}"
    )
    for sc in res["scenarios"]:
        print(f"\n{sc['scenario']}", file=out)
        print(head, file=out)
        for b in sc["bands"]:
            lo, hi = b["band_m"]
            print(
                f"  {f'{lo:g}-{hi:g}':>10} {b['seen']:>6.0%} {b['acquired']:>6.0%} "
                f"{b['error_m_median']:>8.2f} {b['error_m_p90']:>8.2f} "
                f"{b['error_px_median']:>7.1f} {b['forward_m_median']:>+8.2f} "
                f"{b['right_m_median']:>+9.2f} {b['false_seen']:>10.0%} "
                f"{b['false_acquired']:>9.0%}",
                file=out,
            )
