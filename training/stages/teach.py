"""The stages of a run that teaches a pad (``training.pad_teach``): ``perception`` (the CNN
fine-tuned on frames rendered with the pad), ``vision`` (the ``--from`` controller fed by it,
validated; vision DAgger rounds only where validation says so) and ``eval`` (the pad's suite,
taught and ``--from`` model on the same episodes, into ``pad_metrics.json``). They write the
records of the stages of the same names."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from companion.files import sha256_file
from companion.flightlog import jsonable
from companion.policy_net import ESTIMATOR_FIELDS, PerceptionCNN, load_networks, save_checkpoint
from training.pad_teach import (
    PAD_SUITE_EPISODES,
    PAD_VALIDATION_SUCCESS,
    PadMetrics,
    PadTeach,
    SourceRecord,
    read_started_from,
    write_pad_suite,
)
from training.perception_data import PoseSampling
from training.profiles import PipelineError
from training.replay import ReplayBuffer
from training.run_folder import Run
from training.stage_records import (
    EvalRecord,
    FitRecord,
    PerceptionRecord,
    ValidationScore,
    VisionRecord,
)
from training.stages.eval import fly_suite
from training.stages.perception import fit_cnn, pose_frames, save_perception
from training.stages.selection import validate
from training.stages.vision import select_vision, vision_rounds

__all__ = ["evaluate", "perception", "pose_sampling", "vision"]


def _teach(r: Run) -> tuple[PadTeach, SourceRecord]:
    """The run's pad and the model it started from, whose file must still be the one it was
    (sha256)."""
    src = read_started_from(r.root)
    if r.pad is None or src is None:
        raise PipelineError(f"{r.root}: not a run that teaches a pad (visland pipeline --pad)")
    if not Path(src.checkpoint).is_file() or sha256_file(src.checkpoint) != src.sha256:
        raise PipelineError(
            f"{r.root}: the run started from {src.checkpoint} (sha256 {src.sha256[:12]}), which "
            "is gone or has changed since; teach the pad again in a new --out folder"
        )
    return r.pad, src


def pose_sampling(pad: PadTeach, away_fraction: float = 0.0) -> PoseSampling:
    """The pose distribution of perception frames, its altitudes scaled to the pad's envelope
    (the paper pad's 1-110 m become 0.25-27.5 m for a 1 m pad), ``away_fraction`` of them over
    bare ground at distances scaled the same way (``Profile.teach_away_fraction``)."""
    plain = PoseSampling()
    (lo, hi), (near, far) = plain.altitude_m, plain.away_m
    return PoseSampling(
        altitude_m=(lo * pad.scale, hi * pad.scale),
        away_fraction=away_fraction,
        away_m=(near * pad.scale, far * pad.scale),
    )


CLOSE_ALTITUDE_M = (0.3, 1.5)
"""The close frames' altitudes over the paper pad (``Profile.pad_close_fraction``), scaled
with the pad: below the pose frames' 1 m, up to the lowest horizontal fix."""


def close_frames(r: Run, pad: PadTeach, cnn: PerceptionCNN) -> tuple[np.ndarray, np.ndarray]:
    """``pad_close_fraction`` x ``pad_pose_frames`` frames over the pad from
    :data:`CLOSE_ALTITUDE_M` (scaled), each labelled with ``cnn``'s own outputs (bearing,
    pad probability): what the ``--from`` CNN answered there, for the fine-tune to keep."""
    p = r.profile
    n = round(p.pad_close_fraction * p.pad_pose_frames)
    lo, hi = CLOSE_ALTITUDE_M
    close = PoseSampling(altitude_m=(lo * pad.scale, hi * pad.scale), in_view_fraction=1.0)
    images, _, _ = pose_frames(r, n, close, f" from {lo * pad.scale:g}-{hi * pad.scale:g} m")
    cnn.eval()
    with torch.no_grad():
        out = torch.cat([cnn(torch.from_numpy(b).float()) for b in np.array_split(images, 64)])
    out[:, 2] = torch.sigmoid(out[:, 2])  # the visibility logit as the probability it stands for
    return images, out.numpy()


def perception(r: Run) -> PerceptionRecord:
    """Frames at sampled poses in the run's worlds (each with the pad), the ``--from`` model's
    CNN fine-tuned on them alone (90/10 split by frame): ``checkpoints/perception.pt`` carries
    it with the ``--from`` controller."""
    p = r.profile
    pad, src = _teach(r)
    cfg, control, cnn, _ = load_networks(src.checkpoint)
    assert cnn is not None  # checked when the run started (check_source)
    torch.manual_seed(p.seed)
    extra = pose_frames(
        r,
        p.pad_pose_frames,
        pose_sampling(pad, p.teach_away_fraction),
        f" with pad {pad.design.name}",
    )
    held = close_frames(r, pad, cnn) if p.pad_close_fraction > 0.0 else None
    n_train = p.pad_pose_frames - round(0.1 * len(extra[0])) + (len(held[0]) if held else 0)
    steps = p.pad_perception_epochs * max(1, n_train // 64)
    fit = fit_cnn(
        r,
        cnn,
        [],
        p.pad_perception_epochs,
        steps,
        f"teach perception ({pad.design.name})",
        extra,
        lr=p.pad_perception_lr,
        gain=(p.pad_perception_min_gain, 1.2),
        held=held,
    )
    r.say(
        f"perception: validation frames' bearing error median "
        f"{fit.pose_val_bearing_error_px_median:.2f} px, "
        f"p95 {fit.pose_val_bearing_error_px_p95:.2f} px, visibility accuracy "
        f"{fit.pose_val_visibility_accuracy:.3f} ({fit.seconds:.0f} s)"
    )
    data = {
        "pad": pad.record.to_dict(),
        "from": src.to_dict(),
        "pose_frames": str(r.root / "cache" / f"poses_s{p.seed + 7}_n{p.pad_pose_frames}.npz"),
        "fit": fit.to_dict(),
    }
    return save_perception(r, cfg, control, cnn, data, fit)


def vision(r: Run) -> VisionRecord:
    """The ``--from`` controller with the taught CNN and the profile's estimator, its lowest
    horizontal fix scaled with the pad like every altitude (``checkpoints/vision_prior.pt``),
    flown on the validation seeds in the run's worlds. Only
    when it lands fewer than :data:`PAD_VALIDATION_SUCCESS` of them do the profile's vision
    DAgger rounds fly (from it, on the learner's flights alone), stopping after
    ``pad_vision_patience`` rounds in a row that do not beat validation's best; validation picks
    among them."""
    p = r.profile
    pad, _ = _teach(r)
    cfg, control, cnn, _ = load_networks(r.need("perception", PerceptionRecord).checkpoint)
    assert cnn is not None
    run_cfg = r.net_config("vision")
    cfg = replace(cfg, **{k: getattr(run_cfg, k) for k in ESTIMATOR_FIELDS})
    # below min_fix_altitude_m the view is a piece of the pad and a bearing is a guess: an
    # altitude that scales with the pad (1.5 m for the 4 m paper pad, 0.375 m for a 1 m one)
    cfg = replace(cfg, min_fix_altitude_m=run_cfg.min_fix_altitude_m * pad.scale)
    prior = save_checkpoint(
        r.root / "checkpoints" / "vision_prior.pt",
        cfg,
        control,
        cnn,
        r.metadata("vision_prior", {"controller": read_started_from(r.root).to_dict()}),
    )
    score = validate(r, str(prior), camera=True)
    known: dict[str, ValidationScore] = {str(prior): score}
    candidates = [str(prior)]
    fits: list[FitRecord] = []
    if (score.success_rate or 0.0) < PAD_VALIDATION_SUCCESS and p.vision_rounds:
        r.say(
            f"vision: the controller lands {100 * (score.success_rate or 0.0):.0f} % of the "
            f"validation flights (< {100 * PAD_VALIDATION_SUCCESS:.0f} %): "
            f"{p.vision_rounds} vision DAgger round(s) of {p.vision_rollouts} rollouts"
        )
        ctrl = type(control)(cfg)
        ctrl.load_state_dict(control.state_dict())
        buf = ReplayBuffer(p.buffer_capacity, p.segment_steps, seed=p.seed + 51)
        candidates += vision_rounds(
            r, cfg, ctrl, cnn, prior, buf, [], fits, known, patience=p.pad_vision_patience
        )
    elif p.vision_rounds:
        r.say("vision: the controller flies the taught CNN as it is (no DAgger round needed)")
    else:
        r.say(f"vision: profile {p.name!r} flies no vision DAgger round")
    return select_vision(r, candidates, known, fits, rounds_flown=bool(fits))


def evaluate(r: Run) -> EvalRecord:
    """The pad's suite (``<run>/suite.toml``: ``training.pad_teach.pad_suite_text``, at most the
    profile's eval episodes per condition, the evaluation seed) flown by the taught model and by
    the ``--from`` model; the inference timing; ``pad_metrics.json``."""
    from training.stages.eval import inference_timing

    p = r.profile
    pad, src = _teach(r)
    vision_rec = r.need("vision", VisionRecord)
    suite_file = write_pad_suite(
        pad, r.root / "suite.toml", min(PAD_SUITE_EPISODES, p.eval_episodes)
    )
    report = fly_suite(r, vision_rec.checkpoint, "suite.json", suite_file)
    baseline = fly_suite(r, src.checkpoint, "suite_baseline.json", suite_file)
    metrics = PadMetrics(
        profile=p,
        git_commit=r.commit,
        pad=pad.record,
        source=src,
        eval_seed=p.eval_seed,
        suite=str(suite_file),
        report=report,
        baseline=baseline,
        timing=inference_timing(vision_rec.checkpoint),
        perception=r.need("perception", PerceptionRecord),
        vision=vision_rec,
    )
    path = r.root / "pad_metrics.json"
    path.write_text(json.dumps(jsonable(metrics.to_dict()), indent=2))
    return r.finish(EvalRecord(stage="eval", git_commit=r.commit, metrics=str(path)))
