"""``visland soak``: a field day for the companion — one process through many consecutive
flights against the SITL (lockstep), watched from outside.

While :func:`training.exec.fly.fly` flies, the companion's resident memory (``VmRSS``) and open
file descriptors are read from ``/proc/<pid>`` as each flight ends; afterwards each flight's
frame→setpoint latency comes from its log. Judged (:data:`LIMITS`): memory growth after the
``warmup`` flights, descriptors constant after them, and the latency p99 of the last flights
against the first after the warm-up — each the median of a window of per-flight p99s, a tenth
of the flights and at least five (a leak, a growing list, a file left open or a slowing loop
shows up in one of them long before a field day is over).
"""

from __future__ import annotations

import os
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.record import latency_stats
from training.seeds import EVAL_SEED

__all__ = ["LIMITS", "SoakConfig", "SoakReport", "latency_holds", "latency_windows", "soak"]

LIMITS = {"rss_growth_mb": 10.0, "p99_ratio": 2.0, "p99_slack_ms": 2.0, "window_flights": 5}
"""Pass: resident memory grows at most 10 MB after the warm-up; descriptors end as they were
after it; the last window's latency p99 is at most 2 x the first window's + 2 ms. A window is
the median of per-flight p99s over a tenth of the flights after the warm-up, and never fewer
than 5: one flight's p99 is one scheduler's hiccup (a loaded 2-core CI machine moved it from
1.1 to 4.0 ms within 24 flights of an expert companion), while a leak or a slowing loop moves
the median without bound."""


@dataclass(frozen=True)
class SoakConfig:
    flights: int = 500
    policy: str = "expert"
    """What the companion flies (``expert`` needs no camera: the most flights per minute)."""
    seed: int = EVAL_SEED
    scenario: str | None = None
    warmup: int = 20
    """Flights before the memory and descriptor baseline is taken (imports, caches, JITs)."""
    out: str | None = None
    """Run folder (None: a temporary one)."""
    progress: bool = True


@dataclass
class SoakReport:
    flights: int
    success_rate: float
    wall_s: float
    rss_mb: dict[str, float]
    """``warmup`` (after the warm-up flights), ``end``, ``growth``, ``max``."""
    fds: dict[str, int]
    """``warmup``, ``end``, ``max``."""
    latency_p99_ms: dict[str, float]
    """Median of per-flight p99s over the ``first`` window after the warm-up and the ``last``
    window (a tenth of the flights, at least 5); ``max``: the worst single flight's."""
    passed: dict[str, bool]
    samples: list[dict[str, float]] = field(default_factory=list)
    """Per flight ended: ``flight``, ``rss_mb``, ``fds``."""
    out: str = ""

    @property
    def ok(self) -> bool:
        return all(self.passed.values())

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "ok": self.ok}


def _proc_sample(pid: int) -> tuple[float, int] | None:
    """(resident MB, open descriptors) of ``pid``, None once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    kb = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:"))
    return kb / 1024.0, fds


def latency_windows(p99: list[float], warmup: int) -> tuple[float, float]:
    """(first, last): the median per-flight p99 over the first window after ``warmup`` flights
    and over the last window (:data:`LIMITS`)."""
    window = max(LIMITS["window_flights"], (len(p99) - warmup) // 10)
    return float(np.median(p99[warmup : warmup + window])), float(np.median(p99[-window:]))


def latency_holds(first: float, last: float) -> bool:
    return last <= LIMITS["p99_ratio"] * first + LIMITS["p99_slack_ms"]


def soak(cfg: SoakConfig) -> SoakReport:
    """Fly ``cfg.flights`` flights through one companion process and judge it (module doc).

    Raises:
        ValueError: fewer flights than the warm-up plus ten.
        training.exec.fly.FlyError: a process failed.
    """
    from tools.cli_args import config_from_args
    from training.exec.fly import FlyConfig, fly

    least = cfg.warmup + 2 * LIMITS["window_flights"]
    if cfg.flights < least:
        raise ValueError(
            f"--flights {cfg.flights}: expected at least --warmup + {least - cfg.warmup} "
            f"(two latency windows of {LIMITS['window_flights']} flights after the warm-up)"
        )
    samples: dict[int, tuple[float, int]] = {}

    def monitor(pid: int, ended: int) -> None:
        if ended not in samples:
            sample = _proc_sample(pid)
            if sample is not None:
                samples[ended] = sample
                if cfg.progress and ended % 50 == 0:
                    print(
                        f"soak: {ended}/{cfg.flights} flights, companion {sample[0]:.1f} MB, "
                        f"{sample[1]} fds",
                        file=sys.stderr,
                        flush=True,
                    )

    # the soak's policy, seed, scenario and out
    report = fly(
        config_from_args(FlyConfig, cfg, episodes=cfg.flights, progress=False, monitor=monitor)
    )
    logs = sorted((Path(report.out) / "companion").glob("*.mcap"))
    p99 = [latency_stats([log])["p99_ms"] for log in logs]
    after = [n for n in sorted(samples) if n >= cfg.warmup]
    base = samples[after[0]] if after else samples[max(samples)]
    end = samples[max(samples)]
    first, last = latency_windows(p99, cfg.warmup)
    growth = end[0] - base[0]
    return SoakReport(
        flights=report.episodes,
        success_rate=report.summary.success_rate,
        wall_s=report.wall_s,
        rss_mb={
            "warmup": base[0],
            "end": end[0],
            "growth": growth,
            "max": max(s[0] for s in samples.values()),
        },
        fds={"warmup": base[1], "end": end[1], "max": max(s[1] for s in samples.values())},
        latency_p99_ms={"first": first, "last": last, "max": float(max(p99))},
        passed={
            "memory": growth <= LIMITS["rss_growth_mb"],
            "descriptors": end[1] <= base[1],
            "latency": latency_holds(first, last),
            "landings": report.summary.success_rate == 1.0,
        },
        samples=[{"flight": n, "rss_mb": s[0], "fds": s[1]} for n, s in sorted(samples.items())],
        out=str(report.out),
    )


def format_soak(r: SoakReport) -> str:
    mark = {True: "ok", False: "FAILED"}
    return "\n".join(
        [
            f"soak: {r.flights} flights through one companion in {r.wall_s:.0f} s, "
            f"{100 * r.success_rate:.1f} % landed ({mark[r.passed['landings']]})",
            f"  memory: {r.rss_mb['warmup']:.1f} MB after the warm-up, {r.rss_mb['end']:.1f} MB at "
            f"the end: {r.rss_mb['growth']:+.2f} MB (limit +{LIMITS['rss_growth_mb']:.0f}; "
            f"{mark[r.passed['memory']]})",
            f"  descriptors: {r.fds['warmup']} after the warm-up, {r.fds['end']} at the end "
            f"({mark[r.passed['descriptors']]})",
            f"  latency p99 (median of a window's flights): {r.latency_p99_ms['first']:.2f} ms "
            f"first, {r.latency_p99_ms['last']:.2f} ms last (limit "
            f"{LIMITS['p99_ratio']:g} x first + {LIMITS['p99_slack_ms']:g} ms; "
            f"{mark[r.passed['latency']]}), worst flight {r.latency_p99_ms['max']:.2f} ms",
            f"  logs: {r.out}",
        ]
    )
