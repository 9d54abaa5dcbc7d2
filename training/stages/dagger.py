"""Stage ``dagger`` (paper 4.3, stage 1): DAgger rounds ``dagger_r<k>`` — the learner flies,
the expert relabels its flights offline, the buffer aggregates them, the controller is
retrained — then validation picks among BC and every round: ``checkpoints/dagger.pt``.

Every round leaves its learner flight logs (``flights/dagger_r<k>/``), their offline expert
labels (``labels/dagger_r<k>/``) and its own record; a rerun skips finished rounds."""

from __future__ import annotations

from pathlib import Path

from companion.policy_net import load_networks, save_checkpoint
from training.run_folder import Run
from training.stage_records import BcRecord, DaggerRecord, DaggerRoundRecord
from training.stages.fitting import fit_controller, privileged_buffer
from training.stages.flights import episodes, fly, relabel
from training.stages.selection import select
from training.train import privileged_episode

__all__ = ["run"]


def _round(r: Run, k: int, ckpt: Path) -> DaggerRoundRecord:
    p = r.profile
    name = f"dagger_r{k}"
    logs = fly(r, str(ckpt), p.dagger_seed + k, p.dagger_rollouts, name, camera=False)
    pairs = relabel(r, logs, name)
    cfg, control, _, _ = load_networks(ckpt)
    # expert flights, earlier rounds, then this round (FIFO at capacity)
    buf, names = privileged_buffer(r, k, cfg)
    for ep in episodes(r, pairs, images=False):
        buf.add(privileged_episode(ep, cfg))
        names.append(ep.name)
    fit = fit_controller(r, control, buf, p.dagger_steps, p.finetune_lr, name, p.seed + 1 + k)
    out = save_checkpoint(
        r.root / "checkpoints" / f"{name}.pt",
        cfg,
        control,
        None,
        r.metadata(name, {"episodes": names, "fit": fit.to_dict(), "from": str(ckpt)}),
    )
    return r.finish(
        DaggerRoundRecord(
            stage=name,
            git_commit=r.commit,
            checkpoint=str(out),
            rollouts=p.rollouts,
            pairs=tuple((str(a), str(b)) for a, b in pairs),
            fit=fit,
        )
    )


def run(r: Run) -> DaggerRecord:
    bc = r.need("bc", BcRecord)
    ckpt = Path(bc.checkpoint)
    rounds = []
    for k in range(r.profile.dagger_rounds):
        rec = r.done(f"dagger_r{k}")
        if rec is None:
            rec = _round(r, k, ckpt)
        assert isinstance(rec, DaggerRoundRecord)
        ckpt = Path(rec.checkpoint)
        rounds.append(rec)
    # model selection on validation flights (never on the evaluation seeds)
    candidates = [bc.checkpoint] + [x.checkpoint for x in rounds]
    final, selected, scores = select(r, candidates, camera=False, out="dagger")
    return r.finish(
        DaggerRecord(
            stage="dagger",
            git_commit=r.commit,
            rounds=len(rounds),
            checkpoint=final,
            selected=selected,
            validation=scores,
        )
    )
