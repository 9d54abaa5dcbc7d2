"""Stage ``perception`` (paper 4.3, stage 2): the CNN's pad-bearing regression on the expert's
frames (episode split 90/10) plus frames rendered at sampled poses:
``checkpoints/perception.pt``. Its steps (:func:`pose_frames`, :func:`fit_cnn`,
:func:`save_perception`) serve the taught pad's perception stage too
(``training.stages.teach``)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from companion.policy_net import (
    ControlLSTM,
    NetConfig,
    PerceptionCNN,
    save_checkpoint,
)
from training.dataset import Episode
from training.perception_data import PoseSampling, has_site, render_pose_frames, site_weights
from training.run_folder import Run
from training.stage_records import PerceptionRecord
from training.stages.flights import episodes, expert_pairs
from training.train import PerceptionFit, train_perception

__all__ = ["fit_cnn", "pose_frames", "run", "save_perception"]


def pose_frames(
    r: Run, n: int, sampling: PoseSampling | None = None, what: str = ""
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` frames rendered at poses drawn from ``sampling`` (None: the default
    distribution) in the run's worlds, each world with its pad, by the worlds' shares (with
    ``perception_site_share``: the worlds with a site hold that share), cached in
    ``<run>/cache`` under the seed ``profile.seed + 7``; says how many and how long (``what``
    after the count)."""
    p = r.profile
    t0 = time.perf_counter()
    worlds = r.worlds.worlds
    weights = site_weights(
        tuple(w.share for w in worlds),
        tuple(has_site(w.scenario.pad, w.scenario.terrain) for w in worlds),
        p.perception_site_share,
    )
    frames = render_pose_frames(
        n,
        p.seed + 7,
        r.sim.camera,
        cache_dir=r.root / "cache",
        workers=p.workers,
        sampling=PoseSampling() if sampling is None else sampling,
        visuals=tuple(w.scenario.visual for w in worlds),
        weights=weights,
        pads=tuple(w.scenario.pad for w in worlds),
        terrains=tuple(w.scenario.terrain for w in worlds),
    )
    r.say(f"perception: {n} pose-sampled frames{what} ({time.perf_counter() - t0:.0f} s)")
    return frames


def fit_cnn(
    r: Run,
    cnn: PerceptionCNN,
    eps: list[Episode],
    epochs: int,
    steps: int,
    label: str,
    extra: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    **options: Any,
) -> PerceptionFit:
    """``train_perception`` of ``cnn`` on ``eps`` and the ``extra`` pose frames with the
    profile's seed, logged to the run and shown as a bar of ``steps`` called ``label``
    (``options``: train_perception's other keywords)."""
    with r.bar(steps, label) as bar:
        return train_perception(
            cnn,
            eps,
            epochs,
            seed=r.profile.seed,
            log=r.log,
            progress=bar.update,
            extra=extra,
            **options,
        )


def save_perception(
    r: Run,
    cfg: NetConfig,
    control: ControlLSTM,
    cnn: PerceptionCNN,
    data: dict[str, Any],
    fit: PerceptionFit,
) -> PerceptionRecord:
    """``checkpoints/perception.pt`` (``data``: its metadata) and the stage's record."""
    path = save_checkpoint(
        r.root / "checkpoints" / "perception.pt", cfg, control, cnn, r.metadata("perception", data)
    )
    return r.finish(
        PerceptionRecord(
            stage="perception", git_commit=r.commit, checkpoint=str(path), **fit.to_dict()
        )
    )


def run(r: Run) -> PerceptionRecord:
    p = r.profile
    torch.manual_seed(p.seed)
    cfg = r.net_config("vision")
    cnn = PerceptionCNN(cfg)
    eps = episodes(r, expert_pairs(r), images=True)
    extra = None
    if p.perception_pose_frames > 0:
        sampling = PoseSampling(away_fraction=p.perception_away_fraction)
        extra = pose_frames(r, p.perception_pose_frames, sampling)
    n_train = sum(len(range(0, len(e), p.perception_frame_stride)) for e in eps)
    n_train += p.perception_pose_frames
    steps = p.perception_epochs * max(1, int(n_train * 0.9) // 64)
    fit = fit_cnn(
        r,
        cnn,
        eps,
        p.perception_epochs,
        steps,
        "train perception",
        extra,
        frame_stride=p.perception_frame_stride,
    )
    r.say(
        f"perception: val bearing error median {fit.val_bearing_error_px_median:.2f} px, "
        f"p95 {fit.val_bearing_error_px_p95:.2f} px; position error median "
        f"{fit.val_position_error_m_median:.3f} m ({fit.seconds:.0f} s)"
    )
    # the perception checkpoint carries the privileged DAgger controller if it exists yet
    control = ControlLSTM(cfg)
    data = {"episodes": [e.name for e in eps], "fit": fit.to_dict()}
    return save_perception(r, cfg, control, cnn, data, fit)
