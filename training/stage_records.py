"""The on-disk layout of a run's results: the stage records (``stages/<stage>.json``) and
``metrics.json``, as typed records the stages write and the pipeline and the report read.

Each ``stages/<stage>.json`` starts with ``stage`` and ``git_commit`` (the commit that ran it,
``<sha>+dirty`` for uncommitted code); the rest is the stage's own. ``metrics.json`` (the eval
stage) holds the Table 3 rows (``training.evaluate.evaluate``'s reports,
:class:`training.reports.EvalReport`), the inference timing and a copy of the records of the
stages before it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from training.profiles import Profile
from training.record import Record
from training.reports import EvalReport

__all__ = [
    "STAGES",
    "BcRecord",
    "CollectRecord",
    "DaggerRecord",
    "DaggerRoundRecord",
    "EvalRecord",
    "FitRecord",
    "Metrics",
    "PerceptionRecord",
    "PickRecord",
    "Rows",
    "StageRecord",
    "StageRecords",
    "ValidationScore",
    "VisionRecord",
    "record_type",
]

STAGES = ("collect", "bc", "dagger", "perception", "vision", "eval")


# ------------------------------------------------------------------------------ stage records


@dataclass(frozen=True)
class StageRecord(Record):
    """The keys every stage record starts with."""

    stage: str
    git_commit: str


@dataclass(frozen=True)
class CollectRecord(StageRecord):
    """``collect``: the expert flight logs (in episode order)."""

    logs: tuple[str, ...]
    seed: int
    seconds: float


@dataclass(frozen=True)
class FitRecord(Record):
    """One controller fit on the replay buffer (``training.train.train_controller``)."""

    steps: int
    final_loss: float | None
    seconds: float
    buffer_episodes: int
    buffer_steps: int


@dataclass(frozen=True)
class BcRecord(StageRecord):
    """``bc``: the behaviour-cloned privileged controller; the fit's keys inline."""

    checkpoint: str
    fit: FitRecord = field(metadata={"inline": True})


@dataclass(frozen=True)
class DaggerRoundRecord(StageRecord):
    """``dagger_r<k>``: one DAgger round — its learner logs paired with their expert labels,
    and the fit on the aggregated buffer (keys inline)."""

    checkpoint: str
    rollouts: str
    pairs: tuple[tuple[str, str], ...]
    fit: FitRecord = field(metadata={"inline": True})


@dataclass(frozen=True)
class ValidationScore(Record):
    """One candidate's validation flights; score = mean error + 10 m per failed episode."""

    checkpoint: str
    score: float
    mean_error_m: float | None
    success_rate: float | None
    touchdown_speed_mean_m_s: float | None


@dataclass(frozen=True)
class PickRecord(StageRecord):
    """A stage that ends by picking its best candidate on validation flights
    (``training.stages.selection.select``): the pick, copied to ``checkpoints/<stage>.pt``, the
    candidate it is and every candidate's score; the stage's own keys follow."""

    checkpoint: str
    selected: str
    validation: tuple[ValidationScore, ...]


@dataclass(frozen=True)
class DaggerRecord(PickRecord):
    """``dagger``: the validation pick among BC and every round, and the rounds run."""

    rounds: int


@dataclass(frozen=True)
class PerceptionRecord(StageRecord):
    """``perception``: the CNN checkpoint and its fit (``training.train.PerceptionFit``)."""

    checkpoint: str
    epochs: int
    train_images: int
    val_images: int
    val_bearing_error_px_median: float | None
    val_bearing_error_px_p95: float | None
    val_position_error_m_median: float | None
    val_position_error_m_p95: float | None
    val_visibility_accuracy: float | None
    seconds: float
    pose_images: int
    pose_val_bearing_error_px_median: float | None
    pose_val_bearing_error_px_p95: float | None
    pose_val_visibility_accuracy: float | None


@dataclass(frozen=True)
class VisionRecord(PickRecord):
    """``vision``: the validation pick, the fits (vision BC, then each round) and how its
    rounds flew (None without rounds)."""

    fits: tuple[FitRecord, ...]
    rollouts: str | None


@dataclass(frozen=True)
class EvalRecord(StageRecord):
    """``eval``: where ``metrics.json`` is."""

    metrics: str


_TYPES: dict[str, type[StageRecord]] = {
    "collect": CollectRecord,
    "bc": BcRecord,
    "dagger": DaggerRecord,
    "perception": PerceptionRecord,
    "vision": VisionRecord,
    "eval": EvalRecord,
}


def record_type(stage: str) -> type[StageRecord]:
    """The record class of ``stages/<stage>.json`` (``dagger_r<k>`` for a DAgger round)."""
    if stage.startswith("dagger_r") and stage[len("dagger_r") :].isdigit():
        return DaggerRoundRecord
    try:
        return _TYPES[stage]
    except KeyError:
        raise KeyError(f"no stage record {stage!r}; stages are {', '.join(STAGES)}") from None


# ------------------------------------------------------------------------------ metrics.json


@dataclass(frozen=True)
class Rows(Record):
    """The Table 3 rows, in order."""

    expert: EvalReport
    bc: EvalReport
    dagger: EvalReport
    vision: EvalReport

    def items(self) -> list[tuple[str, EvalReport]]:
        return [(name, getattr(self, name)) for name in ("expert", "bc", "dagger", "vision")]

    def __getitem__(self, name: str) -> EvalReport:
        return getattr(self, name)


@dataclass(frozen=True)
class StageRecords(Record):
    """The records of the stages before eval, as they were when it ran (null: not run)."""

    collect: CollectRecord | None
    bc: BcRecord | None
    dagger: DaggerRecord | None
    perception: PerceptionRecord | None
    vision: VisionRecord | None

    def items(self) -> list[tuple[str, StageRecord | None]]:
        return [(s, getattr(self, s)) for s in STAGES if s != "eval"]


@dataclass(frozen=True)
class Metrics(Record):
    """``metrics.json``."""

    profile: Profile
    git_commit: str
    eval_seed: int
    episodes: int
    rows: Rows
    timing: dict[str, Any]
    """``{"policy": training.bench_policy.bench_policy(...), "mpc": expert.bench.bench_mpc()}``,
    kept as those benchmarks write it (the report reads what it shows defensively)."""
    stages: StageRecords
    suite: str | None = field(default=None, metadata={"omit_none": True})
    """The profile's benchmark suite flown by the vision policy: the file of its report
    (``suite.json`` in the run folder, ``training.suite.run_suite``'s JSON); absent without."""
    suite_baseline: str | None = field(default=None, metadata={"omit_none": True})
    """The same suite flown by the profile's ``eval_suite_baseline`` (``suite_baseline.json``)."""
