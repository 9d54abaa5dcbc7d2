"""Stage ``vision`` (paper 4.3, stage 3): CNN + estimator replace ground truth; the LSTM is
fine-tuned on the expert's flights, then in DAgger rounds where the vision policy flies;
validation with the camera picks among those and every privileged controller that landed:
``checkpoints/vision.pt``."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from companion.policy_net import (
    ESTIMATOR_FIELDS,
    ControlLSTM,
    LearnedPolicy,
    NetConfig,
    PerceptionCNN,
    load_networks,
    save_checkpoint,
)
from training.replay import ReplayBuffer
from training.run_folder import Run
from training.stage_records import (
    DaggerRecord,
    FitRecord,
    PerceptionRecord,
    ValidationScore,
    VisionRecord,
)
from training.stages.fitting import fit_controller
from training.stages.flights import episodes, expert_pairs, fly, relabel
from training.stages.selection import select, validate
from training.train import LabelGate, privileged_episode, vision_episode

__all__ = ["privileged_controllers", "run", "select_vision", "vision_rounds"]


def _vision_policy(r: Run) -> tuple[NetConfig, ControlLSTM, PerceptionCNN]:
    _, control, _, _ = load_networks(r.need("dagger", DaggerRecord).checkpoint)
    cfg, _, cnn, _ = load_networks(r.need("perception", PerceptionRecord).checkpoint)
    assert cnn is not None
    # the estimator as the profile sets it now (no weights depend on it)
    run_cfg = r.net_config("vision")
    cfg = replace(cfg, **{k: getattr(run_cfg, k) for k in ESTIMATOR_FIELDS})
    fresh = ControlLSTM(cfg)
    fresh.load_state_dict(control.state_dict())
    return cfg, fresh, cnn


def privileged_controllers(r: Run, cfg: NetConfig) -> list[tuple[str, ControlLSTM]]:
    """The stage-1 checkpoints that landed every validation flight with ground truth
    (all of them if none did), by file stem: the controllers a vision policy can start
    from."""
    dagger = r.need("dagger", DaggerRecord)
    scores = [(s.checkpoint, s.success_rate) for s in dagger.validation] or [
        (dagger.checkpoint, 1.0)
    ]
    good = [s for s in scores if (s[1] or 0.0) >= 1.0] or scores
    out = []
    for checkpoint, _ in good:
        _, control, _, _ = load_networks(checkpoint)
        fresh = ControlLSTM(cfg)
        fresh.load_state_dict(control.state_dict())
        out.append((Path(checkpoint).stem, fresh))
    return out


def vision_rounds(
    r: Run,
    cfg: NetConfig,
    control: ControlLSTM,
    cnn: PerceptionCNN,
    ckpt: Path,
    buf: ReplayBuffer,
    names: list[str],
    fits: list[FitRecord],
    known: dict[str, ValidationScore] | None = None,
    patience: int | None = None,
) -> list[str]:
    """The profile's vision DAgger rounds: round ``k`` flies the latest checkpoint (``ckpt``
    first) with the camera, relabels its flights, adds their CNN + estimator episodes to ``buf``
    (their names to ``names``) and fine-tunes ``control`` (its fit to ``fits``); returns each
    round's checkpoint ``checkpoints/vision_r<k>.pt``.

    ``patience`` (with ``known``, the scores validated so far): each round is validated as it
    ends (its score into ``known``, so selection does not fly it again), and the rounds stop
    after ``patience`` rounds in a row that did not beat the best score before them — a round
    that does not improve on validation says the next one, from it, is not likely to either, and
    each costs a round of rollouts (as an early stop on no improvement does)."""
    p = r.profile
    out = []
    misses = 0
    for k in range(p.vision_rounds):
        if patience is not None and known is not None and misses >= patience:
            r.say(
                f"vision: {misses} round(s) in a row without a better validation score: "
                f"stopping after {k} of {p.vision_rounds} rounds"
            )
            break
        name = f"vision_r{k}"
        logs = fly(r, str(ckpt), p.vision_seed + k, p.vision_rollouts, name, camera=True)
        pairs = relabel(r, logs, name)
        policy = LearnedPolicy(cfg, control, cnn)
        gate = LabelGate() if p.vision_label_gate else None
        steps = learnt = 0.0
        for ep in episodes(r, pairs, images=True):
            b = vision_episode(policy, ep, gate)
            buf.add(b)
            if p.vision_truth_inputs:
                buf.add(privileged_episode(ep, cfg))
            names.append(ep.name)
            steps += len(ep)
            learnt += len(ep) if b.weights is None else float(b.weights.sum())
        if gate is not None:
            r.say(f"{name}: labels learnt at {learnt / max(steps, 1):.0%} of the learner's steps")
        fits.append(
            fit_controller(r, control, buf, p.vision_steps, p.finetune_lr, name, p.seed + 30 + k)
        )
        ckpt = save_checkpoint(
            r.root / "checkpoints" / f"{name}.pt",
            cfg,
            control,
            cnn,
            r.metadata(name, {"episodes": list(names), "fit": fits[-1].to_dict()}),
        )
        out.append(str(ckpt))
        if patience is not None and known is not None:
            best = min((v.score for v in known.values()), default=float("inf"))
            known[str(ckpt)] = validate(r, str(ckpt), camera=True)
            misses = 0 if known[str(ckpt)].score < best else misses + 1
    return out


def run(r: Run) -> VisionRecord:
    p = r.profile
    cfg, control, cnn = _vision_policy(r)
    policy = LearnedPolicy(cfg, control, cnn)
    buf = ReplayBuffer(p.buffer_capacity, p.segment_steps, seed=p.seed + 50)
    names: list[str] = []
    t0 = time.perf_counter()
    for ep in episodes(r, expert_pairs(r), images=True):
        buf.add(vision_episode(policy, ep))
        names.append(ep.name)
    r.say(f"vision features of {len(names)} expert flights: {time.perf_counter() - t0:.0f} s")
    fits = [
        fit_controller(r, control, buf, p.vision_bc_steps, p.finetune_lr, "vision_bc", p.seed + 20)
    ]
    ckpt = save_checkpoint(
        r.root / "checkpoints" / "vision_bc.pt",
        cfg,
        control,
        cnn,
        r.metadata("vision_bc", {"episodes": list(names), "fit": fits[-1].to_dict()}),
    )
    # Candidates 0..: each privileged controller that landed on validation (BC and every
    # DAgger round), as it is, fed by CNN + estimator. Fine-tuning on the expert's flights
    # alone shrinks the controller's gain on the (noisy) position estimate — the expert
    # stays over the pad, so position noise looks uncorrelated with its commands
    # (regression dilution). And privileged validation cannot tell them apart (millimetres
    # for all), while with a noisy estimate a DAgger round's controller — trained on the
    # learner's off-nominal states — can flare where the BC one hits the ground: vision
    # validation decides.
    priors = []
    for name, prior_control in privileged_controllers(r, cfg):
        priors.append(
            str(
                save_checkpoint(
                    r.root / "checkpoints" / f"vision_prior_{name}.pt",
                    cfg,
                    prior_control,
                    cnn,
                    r.metadata("vision_prior", {"controller": name}),
                )
            )
        )
    candidates = [*priors, str(ckpt)]
    known: dict[str, ValidationScore] = {}
    if p.vision_dagger_from_prior and p.vision_rounds:
        # the rounds start from the prior that flies best with the camera, and learn from the
        # learner's own flights only (module docstring of training.profiles, the profile key)
        known = {c: validate(r, c, camera=True) for c in priors}
        best = min(known.values(), key=lambda v: v.score).checkpoint
        _, prior_control, _, _ = load_networks(best)
        control.load_state_dict(prior_control.state_dict())
        ckpt = Path(best)
        buf = ReplayBuffer(p.buffer_capacity, p.segment_steps, seed=p.seed + 51)
        names = []
        r.say(f"vision rounds start from {ckpt.name} (learner flights only)")
    candidates += vision_rounds(r, cfg, control, cnn, ckpt, buf, names, fits)
    return select_vision(r, candidates, known, fits, rounds_flown=bool(p.vision_rounds))


def select_vision(
    r: Run,
    candidates: list[str],
    known: dict[str, ValidationScore],
    fits: list[FitRecord],
    rounds_flown: bool,
) -> VisionRecord:
    """Validation with the camera picks the stage's checkpoint among ``candidates`` (``known``:
    those already validated); the stage's record, with the rollout transport where vision
    DAgger rounds flew (``fits``: the controller's fits)."""
    final, selected, scores = select(r, candidates, camera=True, out="vision", known=known)
    return r.finish(
        VisionRecord(
            stage="vision",
            git_commit=r.commit,
            fits=tuple(fits),
            rollouts=r.profile.rollouts if rounds_flown else None,
            checkpoint=final,
            selected=selected,
            validation=scores,
        )
    )
