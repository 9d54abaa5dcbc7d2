"""Controller fits of the stages: the stage-1 replay buffer (expert flights, then each finished
DAgger round) and one ``train_controller`` call with the run's scalars and progress bar."""

from __future__ import annotations

from pathlib import Path

from companion.policy_net import ControlLSTM, NetConfig
from training.replay import ReplayBuffer
from training.run_folder import Run
from training.stage_records import DaggerRoundRecord, FitRecord
from training.stages.flights import episodes, expert_pairs
from training.train import privileged_episode, train_controller

__all__ = ["fit_controller", "privileged_buffer"]


def privileged_buffer(run: Run, rounds_done: int, cfg: NetConfig) -> tuple[ReplayBuffer, list[str]]:
    """The stage-1 buffer: expert flights then each finished DAgger round, FIFO, as inputs of
    a controller of config ``cfg``."""
    p = run.profile
    buf = ReplayBuffer(p.buffer_capacity, p.segment_steps, seed=p.seed)
    names = []
    for ep in episodes(run, expert_pairs(run), images=False):
        buf.add(privileged_episode(ep, cfg))
        names.append(ep.name)
    for k in range(rounds_done):
        rec = run.need(f"dagger_r{k}", DaggerRoundRecord)
        pairs = [(Path(a), Path(b)) for a, b in rec.pairs]
        for ep in episodes(run, pairs, images=False):
            buf.add(privileged_episode(ep, cfg))
            names.append(ep.name)
    return buf, names


def fit_controller(
    run: Run,
    control: ControlLSTM,
    buf: ReplayBuffer,
    steps: int,
    lr: float,
    tag: str,
    seed: int,
) -> FitRecord:
    """Train ``control`` on ``buf`` for ``steps``; scalars under ``controller/<tag>``."""
    p = run.profile
    with run.bar(steps, f"train {tag}") as bar:
        fit = train_controller(
            control,
            buf,
            steps,
            batch_segments=p.batch_segments,
            lr=lr,
            seed=seed,
            burn_in_steps=p.burn_in_steps,
            log=run.log,
            log_prefix=f"controller/{tag}",
            progress=bar.update,
        )
    run.say(f"{tag}: {steps} steps, loss {fit.final_loss:.4f}, {fit.seconds:.0f} s")
    return FitRecord(
        steps=steps,
        final_loss=fit.final_loss,
        seconds=fit.seconds,
        buffer_episodes=len(buf),
        buffer_steps=buf.total_steps,
    )
