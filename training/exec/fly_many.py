"""Many runs of SITL + companion pairs (``visland fly --instances``, DAgger rollouts over
MAVLink): the episodes cut into runs of consecutive ones, each run a task of a backend.

The caller of :mod:`training.exec.backend` for MAVLink work: it imports the backend, which
runs :func:`training.exec.fly.fly_run` for it.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from training.exec.backend import Backend, LocalBackend
from training.exec.fly import FlyConfig, FlyError, fly_report
from training.reports import BackendInfo, FlyReport

__all__ = ["fly_many"]


def _chunks(indices: list[int], size: int) -> list[tuple[int, int]]:
    """``(first, count)`` runs of consecutive indices, each at most ``size`` long."""
    runs: list[tuple[int, int]] = []
    for i in sorted(set(indices)):
        if runs and runs[-1][0] + runs[-1][1] == i and runs[-1][1] < size:
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((i, 1))
    return runs


def fly_many(
    cfg: FlyConfig,
    indices: list[int],
    instances: int = 2,
    chunk: int = 10,
    on_done: Callable[[int], None] | None = None,
    backend: Backend | None = None,
) -> FlyReport:
    """Fly episodes ``indices`` of ``cfg.seed`` with SITL + companion pairs, each in lockstep
    on its own free ports: up to ``instances`` side by side on this host, or on ``backend``
    (e.g. a Ray cluster: one pair per task, where the cluster has room).

    The indices are cut into runs of at most ``chunk`` consecutive episodes; each run is one
    :func:`~training.exec.fly.fly_run` (its SITL started at ``--first-episode``), so any
    subset of a seed's episodes can be flown (a resumed DAgger round flies only the missing
    ones) and a failed pair loses at most one run. The SITL logs of every run go to
    ``cfg.sitl_log_dir`` (default ``<out>/sitl``); each run's companion logs and process output
    to ``<out>/ep<first>/``.
    ``on_done(n)`` after each run with its episode count.

    Returns the report of :func:`training.exec.fly.fly` over all episodes (``instances``,
    ``runs`` and ``backend`` added).

    Raises:
        FlyError: after every run has been tried, naming each that failed (the episodes of the
            runs that finished keep their logs).
    """
    if not indices:
        raise ValueError("no episodes to fly")
    if instances < 1 or chunk < 1:
        raise ValueError(f"instances and chunk must be >= 1, got {instances}, {chunk}")
    out = Path(cfg.out) if cfg.out else Path(tempfile.mkdtemp(prefix="visland_fly_"))
    sitl_dir = Path(cfg.sitl_log_dir) if cfg.sitl_log_dir else out / "sitl"
    runs = _chunks(indices, chunk)
    backend = backend or LocalBackend(min(instances, len(runs)))
    t0 = time.monotonic()
    reports, failures = backend.fly_runs(cfg, runs, out, sitl_dir, on_done)
    if failures:
        raise FlyError(f"{len(failures)} of {len(runs)} runs failed:\n" + "\n".join(failures))
    rows = sorted((r for rep in reports for r in rep.per_episode), key=lambda r: r.episode)
    flights: dict[str, int] = {}
    for rep in reports:
        for k, v in rep.companion_flights.items():
            flights[k] = flights.get(k, 0) + v
    return fly_report(
        cfg,
        rows,
        sorted(out.glob("ep*/companion/*.mcap")),
        flights,
        instances=min(backend.slots, len(runs)),
        runs=len(runs),
        backend=BackendInfo.from_dict(backend.describe(), "backend"),
        wall_s=time.monotonic() - t0,
        out=str(out),
    )
