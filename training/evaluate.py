"""``visland eval`` and ``visland collect``: fly a policy over the scenario, report or record.

The metrics are ``sitl_sim.metrics`` (one definition everywhere); the reports are
:mod:`training.reports`' records (``EvalReport``, ``CollectReport``), whose fields are their JSON
keys: episodes, transport, seed, landing_error_m {min, max, mean, std}, touchdown_speed_m_s
{...}, success_rate and per_episode rows among them.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from tqdm import tqdm

from sitl_sim.scenario import Scenario
from training.exec.rollout import (
    RolloutSpec,
    completed_episode,
    log_name,
)
from training.exec.transport import Transport
from training.reports import (
    BackendInfo,
    CollectReport,
    EpisodeRow,
    EvalReport,
    FlyReport,
    LandingSummary,
    Stats,
)
from training.seeds import EVAL_SEED

if TYPE_CHECKING:
    from training.exec.backend import Backend

__all__ = ["CollectConfig", "EvalConfig", "collect", "evaluate", "format_table"]


@dataclass(frozen=True)
class EvalConfig:
    """Options of ``visland eval``."""

    policy: str = "expert"
    """``expert`` (MPC), ``cascade`` (PD baseline) or a checkpoint path."""
    episodes: int = 20
    seed: int = EVAL_SEED
    """Evaluation seed; keep it disjoint from training/collection seeds."""
    scenario: str | Scenario | None = None
    """A scenario file (None: ``configs/scenario.toml``) or a checked scenario, e.g. one of a
    benchmark suite's inline conditions (reported by its ``source``)."""
    workers: int = 1
    render_camera: bool = True
    """Render the camera (needed by vision policies; privileged ones can skip it)."""
    progress: bool = True
    backend: Backend | None = None
    """Where the episodes fly (None: this host, ``workers`` processes)."""
    keep_logs: str | None = None
    """Keep flight logs in this folder (None: none are written): each kept flight's MCAP
    (camera, ground truth, observation, command, the policy's estimate) named
    ``<condition>_s<seed>_ep<i>.mcap``, its path in the report's row (``log``)."""
    keep: str = "failed"
    """Which flights ``keep_logs`` keeps: ``failed`` (not a success) or ``all``."""
    condition: str = "eval"
    """The kept logs' name prefix (a suite's condition name)."""
    settings: tuple[tuple[str, Any], ...] = ()
    """A checkpoint's estimator and guard values replaced (``--estimator KEY=VALUE``)."""


KEEP = ("failed", "all")


def _keep_logs(
    cfg: EvalConfig, staging: Path, rows: tuple[EpisodeRow, ...]
) -> tuple[EpisodeRow, ...]:
    """Move the flights ``cfg.keep`` asks for from ``staging`` into ``cfg.keep_logs`` under
    their condition, seed and episode; drop the rest; each row's ``log`` is its kept file."""
    out_dir = Path(str(cfg.keep_logs))
    kept: list[EpisodeRow] = []
    moved: list[tuple[Path, str | None]] = []  # (kept log, policy to draw it with)
    for row in rows:
        src = staging / log_name(cfg.seed, row.episode)
        path = None
        if src.exists() and (cfg.keep == "all" or not row.success):
            dst = out_dir / f"{cfg.condition}_s{cfg.seed}_ep{row.episode:04d}.mcap"
            src.replace(dst)
            moved.append((dst, None))
            path = str(dst)
        kept.append(replace(row, log=path))
    shutil.rmtree(staging, ignore_errors=True)
    if moved:
        # a kept log opens in Foxglove as a live flight does (companion.live.scene_log)
        from companion.live.scene_log import add_scenes

        add_scenes(moved, "visland eval")
    return tuple(kept)


def _fly(
    spec: RolloutSpec,
    indices: list[int],
    backend: Backend | None,
    workers: int,
    progress: bool,
    desc: str,
) -> dict[str, Any]:
    """Fly episodes ``indices`` of ``spec`` on ``backend`` (None: this host, ``workers``
    processes); the in-process part of the report: the summary, the policy's counters summed,
    the wall time, where they flew and one row per episode."""
    from training.exec.backend import LocalBackend

    backend = backend if backend is not None else LocalBackend(workers)
    t0 = time.perf_counter()
    with tqdm(
        total=len(indices), desc=desc, unit="ep", file=sys.stderr, disable=not progress
    ) as bar:
        outcomes = backend.episodes(spec, indices, lambda _: bar.update()) if indices else []
    totals: dict[str, int] = {}
    for o in outcomes:
        for k, v in o.policy_stats.items():
            totals[k] = totals.get(k, 0) + v
    return {
        "summary": LandingSummary.of([o.result for o in outcomes]),
        "policy_stats": totals,
        "wall_s": time.perf_counter() - t0,
        "backend": BackendInfo.from_dict(backend.describe(), "backend"),
        "per_episode": tuple(o.row() for o in outcomes),
    }


def _scenario_name(scenario: str | Scenario | None) -> str:
    if isinstance(scenario, Scenario):
        return scenario.source
    return scenario or "configs/scenario.toml"


def evaluate(cfg: EvalConfig) -> EvalReport:
    if cfg.episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {cfg.episodes}")
    if cfg.keep not in KEEP:
        raise ValueError(f"keep = {cfg.keep!r}; expected one of {KEEP}")
    staging = None
    if cfg.keep_logs is not None:
        Path(cfg.keep_logs).mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{cfg.condition}_", dir=cfg.keep_logs))
    spec = RolloutSpec(
        policy=cfg.policy,
        seed=cfg.seed,
        scenario=cfg.scenario,
        render_camera=cfg.render_camera,
        log_dir=None if staging is None else str(staging),
        settings=cfg.settings,
    )
    desc = f"eval {cfg.policy}"
    flown = _fly(spec, list(range(cfg.episodes)), cfg.backend, cfg.workers, cfg.progress, desc)
    if staging is not None:
        flown["per_episode"] = _keep_logs(cfg, staging, flown["per_episode"])
    return EvalReport(
        policy=cfg.policy,
        transport=Transport.INPROCESS.value,
        seed=cfg.seed,
        scenario=_scenario_name(cfg.scenario),
        episodes=len(flown["per_episode"]),
        estimator=dict(cfg.settings) or None,
        **flown,
    )


@dataclass(frozen=True)
class CollectConfig:
    """Options of ``visland collect``."""

    out: Path
    """Run folder; logs go to ``<out>/flights/``."""
    episodes: int = 300
    seed: int = 0
    scenario: str | None = None
    workers: int = 1
    policy: str = "expert"
    progress: bool = True
    backend: Backend | None = None
    """Where the episodes fly (None: this host, ``workers`` processes)."""


def collect(cfg: CollectConfig) -> CollectReport:
    """Fly the expert and write one flight log per episode; resumable (skips complete logs)."""
    flights = Path(cfg.out) / "flights"
    flights.mkdir(parents=True, exist_ok=True)
    todo, done = [], []
    for i in range(cfg.episodes):
        (done if completed_episode(flights / log_name(cfg.seed, i)) else todo).append(i)
    spec = RolloutSpec(
        policy=cfg.policy, seed=cfg.seed, scenario=cfg.scenario, log_dir=str(flights)
    )
    flown = _fly(spec, todo, cfg.backend, cfg.workers, cfg.progress, f"collect {cfg.policy}")
    report = CollectReport(
        policy=cfg.policy,
        seed=cfg.seed,
        scenario=_scenario_name(cfg.scenario),
        episodes=cfg.episodes,
        flown_now=len(todo),
        already_complete=len(done),
        flights_dir=str(flights),
        **flown,
    )
    # as json.dumps writes it (NaN as NaN, as this file always had it)
    (Path(cfg.out) / f"collect_s{cfg.seed}.json").write_text(json.dumps(report.to_dict(), indent=2))
    return report


def format_table(report: EvalReport | CollectReport | FlyReport, out: TextIO) -> None:
    """A human summary of an eval, collect (the episodes flown now) or fly report."""
    n = report.flown_now if isinstance(report, CollectReport) else report.episodes
    s = report.summary
    timeouts = s.timeouts
    landed = n - timeouts if s.landed is None else s.landed

    def row(name: str, stats: Stats, unit: str, landed_only: bool = False) -> None:
        if stats.mean is None or math.isnan(stats.mean):  # nothing touched down: no statistic
            why = f"none of {n} episodes touched down" if landed_only and n else "no value"
            out.write(f"  {name:<22} n/a ({why})\n")
            return
        up = n - landed
        over = f" (over {landed} landed; {up} never touched down)" if landed_only and up else ""
        out.write(
            f"  {name:<22} min {stats.min:8.3f}  max {stats.max:8.3f}  mean {stats.mean:8.3f}"
            f"  std {stats.std:8.3f} {unit}{over}\n"
        )

    where = f", scenario {report.scenario}" if report.scenario else ""
    out.write(f"{report.policy}: {n} episodes, seed {report.seed}{where}\n")
    row("landing error", s.landing_error_m, "m", landed_only=True)
    row("touchdown speed", s.touchdown_speed_m_s, "m/s", landed_only=True)
    row("tilt at touchdown", s.tilt_deg, "deg", landed_only=True)
    row("time to touchdown", s.time_s, "s")
    counters = {} if isinstance(report, FlyReport) else report.policy_stats
    unsafe = "" if s.off_pad is None else f"   off pad {s.off_pad}   aborts {s.aborts}"
    held = f"   not started {s.not_started} (HOLD timeout)" if s.not_started else ""
    out.write(
        f"  success rate {100 * s.success_rate:.1f} %{unsafe}   timeouts {timeouts}{held}"
        f"   policy counters {counters}\n"
    )
    kept = [
        r for r in getattr(report, "per_episode", ()) if r.log and not isinstance(report, FlyReport)
    ]
    if kept:
        out.write(f"  flight logs kept ({len(kept)}):\n")
        for r in kept:
            err = "n/a" if r.landing_error_m is None else f"{r.landing_error_m:.2f} m"
            out.write(f"    episode {r.episode:4d}  {r.verdict():<13} error {err:>9}  {r.log}\n")
