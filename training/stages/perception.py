"""Stage ``perception`` (paper 4.3, stage 2): the CNN's pad-bearing regression on the expert's
frames (episode split 90/10) plus frames rendered at sampled poses:
``checkpoints/perception.pt``."""

from __future__ import annotations

import time

import torch

from companion.policy_net import ControlLSTM, PerceptionCNN, save_checkpoint
from training.perception_data import render_pose_frames
from training.run_folder import Run
from training.stage_records import PerceptionRecord
from training.stages.flights import episodes, expert_pairs
from training.train import train_perception

__all__ = ["run"]


def run(r: Run) -> PerceptionRecord:
    p = r.profile
    torch.manual_seed(p.seed)
    cfg = r.net_config("vision")
    cnn = PerceptionCNN(cfg)
    eps = episodes(r, expert_pairs(r), images=True)
    extra = None
    if p.perception_pose_frames > 0:
        t0 = time.perf_counter()
        worlds = r.worlds.worlds
        extra = render_pose_frames(
            p.perception_pose_frames,
            p.seed + 7,
            r.sim.camera,
            cache_dir=r.root / "cache",
            workers=p.workers,
            visuals=tuple(w.scenario.visual for w in worlds),
            weights=tuple(w.share for w in worlds),
            pads=tuple(w.scenario.pad for w in worlds),
        )
        r.say(
            f"perception: {p.perception_pose_frames} pose-sampled frames "
            f"({time.perf_counter() - t0:.0f} s)"
        )
    n_train = sum(len(range(0, len(e), p.perception_frame_stride)) for e in eps)
    n_train += p.perception_pose_frames
    steps = p.perception_epochs * max(1, int(n_train * 0.9) // 64)
    with r.bar(steps, "train perception") as bar:
        fit = train_perception(
            cnn,
            eps,
            p.perception_epochs,
            seed=p.seed,
            frame_stride=p.perception_frame_stride,
            log=r.log,
            progress=bar.update,
            extra=extra,
        )
    r.say(
        f"perception: val bearing error median {fit.val_bearing_error_px_median:.2f} px, "
        f"p95 {fit.val_bearing_error_px_p95:.2f} px; position error median "
        f"{fit.val_position_error_m_median:.3f} m ({fit.seconds:.0f} s)"
    )
    # the perception checkpoint carries the privileged DAgger controller if it exists yet
    control = ControlLSTM(cfg)
    path = save_checkpoint(
        r.root / "checkpoints" / "perception.pt",
        cfg,
        control,
        cnn,
        r.metadata("perception", {"episodes": [e.name for e in eps], "fit": fit.to_dict()}),
    )
    return r.finish(
        PerceptionRecord(
            stage="perception", git_commit=r.commit, checkpoint=str(path), **fit.to_dict()
        )
    )
