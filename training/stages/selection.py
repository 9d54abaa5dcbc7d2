"""Model selection: fly candidates on the validation seed (never the evaluation seed) and keep
the best as ``checkpoints/<name>.pt``."""

from __future__ import annotations

import math
from pathlib import Path

from training.reports import LandingSummary
from training.run_folder import Run
from training.stage_records import ValidationScore

__all__ = ["evaluate", "select", "validate"]


def evaluate(
    run: Run, policy: str, episodes: int, seed: int, camera: bool, progress: bool
) -> tuple[LandingSummary, dict[str, LandingSummary]]:
    """``training.evaluate.evaluate`` on this run's scenario and workers; across worlds, each
    world flies its share of ``episodes`` on its seed. Returns the summary of every episode
    flown, and across worlds each world's own (none with one world)."""
    from training.evaluate import EvalConfig
    from training.evaluate import evaluate as evaluate_policy

    reports = {
        world.name: evaluate_policy(
            EvalConfig(
                policy=policy,
                episodes=n,
                seed=seed + world.seed_offset,
                scenario=world.file,
                render_camera=camera,
                progress=progress,
                backend=run.backend,
            )
        )
        for world, n in run.worlds.split(episodes)
        if n > 0
    }
    if len(reports) == 1:
        return next(iter(reports.values())).summary, {}
    pooled = [row.result() for r in reports.values() for row in r.per_episode]
    return LandingSummary.of(pooled), {name: r.summary for name, r in reports.items()}


def validate(run: Run, checkpoint: str, camera: bool) -> ValidationScore:
    """Fly the validation episodes; score = mean error + 10 m per failed episode."""
    p = run.profile
    rep, worlds = evaluate(run, checkpoint, p.validation_episodes, p.validation_seed, camera, False)
    mean = rep.landing_error_m.mean  # over the landed episodes; NaN: none landed
    landed = mean is not None and math.isfinite(mean)
    score = (mean if landed else 100.0) + 10.0 * (1.0 - rep.success_rate)
    per_world = "".join(f"; {name} {100 * w.success_rate:.0f} %" for name, w in worlds.items())
    run.say(
        f"validation {Path(checkpoint).name}: score {score:.3f} (mean error "
        f"{mean if landed else float('nan'):.3f} m, success "
        f"{100 * rep.success_rate:.0f} %{per_world})"
    )
    return ValidationScore(
        checkpoint=checkpoint,
        score=score,
        mean_error_m=mean,
        success_rate=rep.success_rate,
        touchdown_speed_mean_m_s=rep.touchdown_speed_m_s.mean,
    )


def select(
    run: Run,
    candidates: list[str],
    camera: bool,
    out: str,
    known: dict[str, ValidationScore] | None = None,
) -> tuple[str, str, tuple[ValidationScore, ...]]:
    """Copy the candidate with the best validation score to ``checkpoints/<out>.pt``; returns
    (that file, the candidate chosen, every candidate's score). ``known``: scores already
    flown this stage (same episodes), by checkpoint, not flown again."""
    from companion.policy_net import load_networks, save_checkpoint

    known = known or {}
    scores = tuple(known.get(c) or validate(run, c, camera=camera) for c in candidates)
    best = min(scores, key=lambda r: r.score)
    final = run.root / "checkpoints" / f"{out}.pt"
    cfg, control, cnn, meta = load_networks(best.checkpoint)
    save_checkpoint(
        final, cfg, control, cnn, {**meta, "selected_from": [s.to_dict() for s in scores]}
    )
    return str(final), best.checkpoint, scores
