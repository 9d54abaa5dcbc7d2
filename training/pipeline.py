"""The training schedule of paper 4.3 on a CPU, as resumable stages of one run folder.

    collect     expert flights with camera (in process)                 flights/expert/
    bc          stage 1: privileged LSTM, behaviour cloning             checkpoints/bc.pt
    dagger      stage 1: DAgger rounds (learner flies, relabel, aggregate, retrain)
                                                                        checkpoints/dagger.pt
    perception  stage 2: CNN bearing regression on expert frames (90/10) checkpoints/perception.pt
    vision      stage 3: CNN + estimator replace ground truth; LSTM fine-tuned with DAgger rounds
                where the vision policy flies                           checkpoints/vision.pt
    eval        300 episodes (profile) of expert, BC, DAgger, vision on seeds disjoint from
                training, inference timings                             metrics.json

Each finished stage writes ``stages/<stage>.json``; a rerun skips finished stages (and finished
DAgger rounds), so an interrupted pipeline resumes where it stopped. ``pipeline_time.json`` keeps
each session's seconds, in all and per stage.

With ``pad`` (``visland pipeline --pad PADFILE --from RUN``) the run teaches a new pad to
``RUN``'s controller: stages ``perception``, ``vision``, ``eval`` of ``training.stages.teach``
in the profile's worlds with the pad (``training.pad_teach``). Every DAgger round leaves
its learner flight logs (``flights/<round>/``) and their offline expert labels
(``labels/<round>/``, written by ``expert.relabel`` exactly as ``visland relabel`` does).
Scalars go to TensorBoard (``tb/``) and ``scalars.jsonl``.

The run folder is ``training.run_folder``, the budgets ``training.profiles``, each stage a
module of ``training.stages`` returning its typed record (``training.stage_records``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from training.exec.backend import Backend
from training.profiles import PROFILES, PipelineError, Profile
from training.run_folder import Run
from training.stage_records import STAGES, StageRecord
from training.stages import bc, collect, dagger, perception, teach, vision
from training.stages import eval as eval_stage

STAGE_THREADS = torch.get_num_threads()
"""Torch's threads for every stage: the process's default, taken when the pipeline is imported.
A stage that flies a policy in this process (the eval stage's timing, an in-process rollout)
sets one thread and would leave it set; a later stage then trains with another reduction order
and rounds differently, so a run resumed in a new process, or run twice in one, would not train
the same weights. Each stage starts from this count instead."""

__all__ = ["STAGES", "PipelineError", "Profile", "run_pipeline"]

_STAGE_RUN: dict[str, Callable[[Run], StageRecord]] = {
    "collect": collect.run,
    "bc": bc.run,
    "dagger": dagger.run,
    "perception": perception.run,
    "vision": vision.run,
    "eval": eval_stage.run,
}

_PAD_STAGE_RUN: dict[str, Callable[[Run], StageRecord]] = {
    "perception": teach.perception,
    "vision": teach.vision,
    "eval": teach.evaluate,
}


def run_pipeline(
    out: str | Path,
    profile: str | Profile = "quick",
    scenario: str | None = None,
    stages: tuple[str, ...] | None = None,
    progress: bool = True,
    redo: str | None = None,
    backend: Backend | None = None,
    start_from: str | Path | None = None,
    pad: str | Path | None = None,
) -> dict[str, dict[str, Any]]:
    """Run (or resume) the stages in order; returns the stage records (their JSON).

    ``backend``: where the episodes fly (default: this host, the profile's ``workers``).

    ``redo``: run this stage again although it has finished; the records of the stages after it
    (which were built on it) are removed too, so they run again when asked for.

    ``start_from``: a finished run whose trained stages a new run folder takes
    (:meth:`Run.start_from`: an estimator ablation without training again); with ``pad``, the
    run or checkpoint whose controller learns the pad.

    ``pad``: a pad file (or a shipped pad's name) to teach (module docstring); its stages are
    ``perception``, ``vision``, ``eval`` (``stages``: None, all of a run's stages).

    Raises:
        PipelineError: a stage cannot run; ConfigError: a bad pad file (named).
    """
    from training.pad_teach import PAD_STAGES, teach_pad

    prof = PROFILES[profile] if isinstance(profile, str) else profile
    taught = teach_pad(pad) if pad is not None else None  # a bad file fails before any folder
    if stages is None:
        stages = PAD_STAGES if taught is not None else STAGES
    run = Run(out, prof, scenario, progress, backend=backend, pad=taught)
    try:
        if start_from is not None:
            run.start_from(start_from)
        if taught is not None:
            _check_pad_run(run, stages, PAD_STAGES)
    except PipelineError:
        run.close()
        raise
    if redo is not None:
        if redo not in STAGES:
            run.close()
            raise PipelineError(f"unknown stage {redo!r}; stages are {', '.join(STAGES)}")
        for later in STAGES[STAGES.index(redo) :]:
            record = run.record_path(later)
            if record.exists():
                record.unlink()
                run.say(f"stage {later}: record removed, it will run again")
    records = {}
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    runners = _PAD_STAGE_RUN if taught is not None else _STAGE_RUN
    try:
        for stage in stages:
            if stage not in STAGES:
                raise PipelineError(f"unknown stage {stage!r}; stages are {', '.join(STAGES)}")
            rec = run.done(stage)
            if rec is not None:
                run.say(f"stage {stage}: already done")
            else:
                s0 = time.perf_counter()
                torch.set_num_threads(STAGE_THREADS)
                run.say(f"stage {stage}: running")
                rec = runners[stage](run)
                seconds[stage] = time.perf_counter() - s0
                run.say(f"stage {stage}: done in {seconds[stage]:.0f} s")
            records[stage] = rec.to_dict()
    finally:
        run.close()
    timing_path = Path(out) / "pipeline_time.json"
    prev = json.loads(timing_path.read_text()) if timing_path.exists() else {"sessions": []}
    prev["sessions"].append(
        {"stages": list(stages), "seconds": time.perf_counter() - t0, "stage_seconds": seconds}
    )
    timing_path.write_text(json.dumps(prev, indent=2))
    return records


def _check_pad_run(run: Run, stages: tuple[str, ...], pad_stages: tuple[str, ...]) -> None:
    """A pad run has been started from a model and runs only its own stages."""
    from training.pad_teach import read_started_from

    if read_started_from(run.root) is None:
        raise PipelineError(
            f"{run.root}: --pad needs --from RUN or --from CHECKPOINT: the controller that "
            "learns the pad (e.g. --from models/visland_vision.pt)"
        )
    other = [s for s in stages if s not in pad_stages]
    if other:
        raise PipelineError(
            f"{run.root}: a run that teaches a pad has the stages {', '.join(pad_stages)}; "
            f"got {', '.join(other)}"
        )
