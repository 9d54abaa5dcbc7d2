"""The reports of ``visland eval`` (a suite's included), ``collect`` and ``fly`` as typed records.

Each report is a frozen :class:`~training.record.Record`: its fields are the keys of its
``--json`` document in order, ``to_json()`` writes that document (NaN as null) and
``from_dict`` reads one back, checked (``metrics.json``'s Table 3 rows and a run's
``suite.json`` are these reports). The statistics every report carries are one
:class:`LandingSummary`, inline: ``sitl_sim.metrics.summarize`` (the one definition of the
landing metrics) but the episode count, which each report places itself.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sitl_sim.metrics import EpisodeResult, summarize
from training.record import Record

__all__ = [
    "BackendInfo",
    "CollectReport",
    "EpisodeRow",
    "EvalReport",
    "FlyReport",
    "LandingSummary",
    "Stats",
    "SuiteReport",
]

_INLINE = {"inline": True}
_OMIT = {"omit_none": True}


@dataclass(frozen=True)
class Stats(Record):
    """min/max/mean/std of one metric over the episodes (NaN, null in JSON: no finite value)."""

    min: float | None
    max: float | None
    mean: float | None
    std: float | None


@dataclass(frozen=True, kw_only=True)
class LandingSummary(Record):
    """:func:`sitl_sim.metrics.summarize` but ``episodes``: how many landed, each metric's
    statistics (landing error, touchdown speeds and tilt over the landed episodes), success
    rate and timeouts."""

    landed: int | None = field(default=None, metadata=_OMIT)
    """Episodes the landing-error, touchdown-speed and tilt statistics cover (the rest timed
    out); absent in runs evaluated before timeouts were left out of them."""
    landing_error_m: Stats
    touchdown_speed_m_s: Stats
    touchdown_vertical_speed_m_s: Stats
    tilt_deg: Stats
    time_s: Stats
    success_rate: float | None
    timeouts: int
    aborts: int | None = field(default=None, metadata=_OMIT)
    """Flights the pilot ended in the air (pad not found): failures, not touchdowns; absent
    in reports written before the landing guard."""
    off_pad: int | None = field(default=None, metadata=_OMIT)
    """Touchdowns more than 2 m from the pad (``sitl_sim.metrics.OFF_PAD_M``): the unsafe
    failures; absent in reports written before they were counted."""
    not_started: int | None = field(default=None, metadata=_OMIT)
    """SITL episodes nobody took over from HOLD (a companion that never engaged): failures
    counted apart from ``timeouts``; absent in reports written before they were."""

    @classmethod
    def of(cls, results: Sequence[EpisodeResult]) -> LandingSummary:
        stats = summarize(list(results))
        del stats["episodes"]
        return cls.from_dict(stats, "summarize")


@dataclass(frozen=True)
class EpisodeRow(Record):
    """One episode of a report: ``sitl_sim.metrics.EpisodeResult`` inline; in process, where
    the landing error was measured, the steps and the policy's counters (``policy_<name>``);
    over MAVLink, the impaired link's counts where the run had one."""

    seed: int
    episode: int
    landed: bool
    time_s: float | None
    landing_error_m: float | None
    touchdown_speed_m_s: float | None
    touchdown_vertical_speed_m_s: float | None
    tilt_deg: float | None
    success: bool
    touched_pad: bool | None = field(default=None, metadata=_OMIT)
    """On a site: the vehicle came down on the pad's own surface (absent on the nominal one)."""
    tipped_over: bool | None = field(default=None, metadata=_OMIT)
    """On a site: the surface it came down on was too steep to stand on."""
    failsafe: str | None = field(default=None, metadata=_OMIT)
    """Why the pilot ended the flight in the air (``pad_not_found``); absent otherwise."""
    took_over: bool | None = field(default=None, metadata=_OMIT)
    """False: the SITL episode ended in HOLD, nobody took over; absent otherwise."""
    touchdown_ne_m: tuple[float, float] | None = field(
        default=None, metadata={"omit_none": True, "what": "[north, east] in m"}
    )
    """Where the landing error was measured; absent in runs evaluated before it was recorded."""
    steps: int | None = field(default=None, metadata=_OMIT)
    """Control steps flown (in process; absent in a MAVLink run's rows)."""
    log: str | None = None
    policy_counts: dict[str, int] = field(default_factory=dict, metadata={"prefix": "policy_"})
    link_impairment: dict[str, Any] | None = field(default=None, metadata=_OMIT)
    """The impaired link's config and per-stream counts in this episode (MAVLink, real time)."""

    def result(self) -> EpisodeResult:
        """The episode's result (a null metric is NaN again)."""
        return EpisodeResult.read(self.to_dict())

    def verdict(self) -> str:
        """A word for a table: ``success``, the failsafe that ended it in the air (an abort,
        e.g. ``pad_not_found``), ``not_started`` (nobody took over from the SITL's HOLD),
        ``timeout``, or ``failed`` (landed, not a success)."""
        if self.success:
            return "success"
        if self.failsafe:
            return self.failsafe
        if self.took_over is False:
            return "not_started"
        return "failed" if self.landed else "timeout"


@dataclass(frozen=True)
class BackendInfo(Record):
    """Where a report's episodes flew (``training.exec.backend.Backend.describe``)."""

    name: str
    slots: int
    retried: tuple[str, ...]
    address: str | None = field(default=None, metadata={"omit_none": True})


@dataclass(frozen=True, kw_only=True)
class EvalReport(Record):
    """``visland eval --json`` (``training.evaluate.evaluate``): one policy over one scenario,
    in process; also a Table 3 row of ``metrics.json`` and a suite condition's report."""

    policy: str
    transport: str
    seed: int
    scenario: str
    episodes: int
    summary: LandingSummary = field(metadata=_INLINE)
    policy_stats: dict[str, int]
    wall_s: float
    backend: BackendInfo | None = field(default=None, metadata=_OMIT)
    """Absent in runs evaluated before execution backends existed."""
    estimator: dict[str, Any] | None = field(default=None, metadata=_OMIT)
    """The checkpoint's estimator and guard values this evaluation replaced
    (``--estimator``); absent when it flew the checkpoint's own."""
    per_episode: tuple[EpisodeRow, ...]


@dataclass(frozen=True, kw_only=True)
class CollectReport(Record):
    """``visland collect --json`` (``training.evaluate.collect``): the summary covers the
    episodes flown now (``flown_now`` of ``episodes``; the rest were complete already)."""

    policy: str
    seed: int
    scenario: str
    episodes: int
    flown_now: int
    already_complete: int
    flights_dir: str
    summary: LandingSummary = field(metadata=_INLINE)
    policy_stats: dict[str, int]
    wall_s: float
    backend: BackendInfo
    per_episode: tuple[EpisodeRow, ...]


@dataclass(frozen=True, kw_only=True)
class FlyReport(Record):
    """``visland fly --json`` (``training.exec.fly.fly``; ``fly_many`` adds ``instances``,
    ``runs`` and ``backend``): SITL + companion processes over UDP, results from the SITL's
    logs, the companion's latency figures and flight outcomes."""

    policy: str
    transport: str
    seed: int
    scenario: str
    realtime: bool
    companion_mode: str
    autopilot: str
    episodes: int
    summary: LandingSummary = field(metadata=_INLINE)
    latency_ms: dict[str, Any]
    companion_flights: dict[str, int]
    link_impairment: dict[str, dict[str, int]] | None = field(default=None, metadata=_OMIT)
    """Per stream, each counter summed over the episodes that had an impaired link."""
    instances: int | None = field(default=None, metadata=_OMIT)
    runs: int | None = field(default=None, metadata=_OMIT)
    backend: BackendInfo | None = field(default=None, metadata=_OMIT)
    wall_s: float
    out: str
    per_episode: tuple[EpisodeRow, ...]


@dataclass(frozen=True, kw_only=True)
class SuiteReport(Record):
    """``visland eval --suite FILE --json`` (``training.suite.run_suite``): each condition's
    :class:`EvalReport` by name, in file order (``episodes``: the suite's default count; each
    report says its own). The eval stage's ``suite.json`` adds the policy's sha256."""

    suite: str
    policy: str
    seed: int
    episodes: int
    conditions: dict[str, EvalReport]
    policy_sha256: str | None = field(default=None, metadata=_OMIT)

    @classmethod
    def load(cls, path: str | Path) -> SuiteReport:
        """The report in a JSON file (a run's ``suite.json``), checked."""
        return cls.from_dict(json.loads(Path(path).read_text()), str(path))
