"""The robust policy's acceptance on the benchmark suite: issue 16's targets per condition, and
the suite table of a policy beside a baseline's (the paper-world model), as markdown for
``docs/results.md`` and the model card. Every number is read from ``run_suite`` reports."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

__all__ = ["SUITE_TARGETS", "SuiteTarget", "suite_comparison", "suite_standing"]


@dataclass(frozen=True)
class SuiteTarget:
    """``report["conditions"][condition][metric][stat] <op> limit`` (``stat`` None: a scalar;
    ``condition`` ``*``: every condition of the suite)."""

    condition: str
    metric: str
    stat: str | None
    op: str
    limit: float
    unit: str

    def describe(self, condition: str | None = None) -> str:
        what = {"success_rate": "success", "landing_error_m": "error"}.get(self.metric, self.metric)
        if self.stat and self.metric != "touchdown_speed_m_s":
            what = f"{what} {self.stat}"
        elif self.metric == "touchdown_speed_m_s":
            what = f"touchdown speed {self.stat}"
        limit = f"{100 * self.limit:g} %" if self.unit == "%" else f"{self.limit:g} {self.unit}"
        return f"{condition or self.condition}: {what} {'≤' if self.op == '<=' else '≥'} {limit}"

    def value(self, report: dict[str, Any], condition: str) -> float | None:
        r = report["conditions"].get(condition)
        if r is None:
            return None
        v = r.get(self.metric)
        if self.stat is not None:
            v = (v or {}).get(self.stat)
        return None if v is None else float(v)

    def met(self, value: float | None) -> bool:
        if value is None or not math.isfinite(value):
            return False
        return value <= self.limit if self.op == "<=" else value >= self.limit


SUITE_TARGETS: tuple[SuiteTarget, ...] = (
    SuiteTarget("nominal", "landing_error_m", "mean", "<=", 0.15, "m"),
    SuiteTarget("nominal", "landing_error_m", "max", "<=", 0.5, "m"),
    SuiteTarget("nominal", "success_rate", None, ">=", 0.997, "%"),
    SuiteTarget("mars", "success_rate", None, ">=", 0.99, "%"),
    SuiteTarget("mars", "landing_error_m", "mean", "<=", 0.3, "m"),
    SuiteTarget("wind_moderate_gusts", "success_rate", None, ">=", 0.98, "%"),
    SuiteTarget("wind_moderate_gusts", "landing_error_m", "mean", "<=", 0.4, "m"),
    SuiteTarget("unseen_terrain", "success_rate", None, ">=", 0.98, "%"),
    SuiteTarget("unseen_terrain", "landing_error_m", "mean", "<=", 0.4, "m"),
    SuiteTarget("low_sun", "success_rate", None, ">=", 0.98, "%"),
    SuiteTarget("low_sun", "landing_error_m", "mean", "<=", 0.4, "m"),
    SuiteTarget("sensor_latency_dropouts", "success_rate", None, ">=", 0.98, "%"),
    SuiteTarget("heavy_vehicle", "success_rate", None, ">=", 0.98, "%"),
    SuiteTarget("light_vehicle", "success_rate", None, ">=", 0.98, "%"),
    SuiteTarget("*", "touchdown_speed_m_s", "mean", "<=", 0.6, "m/s"),
)
"""Issue 16's acceptance table for the vision policy on ``configs/suites/standard.toml``."""


def _fmt(v: float | None, unit: str) -> str:
    if v is None or not math.isfinite(v):
        return "n/a"
    return f"{100 * v:.1f} %" if unit == "%" else f"{v:.3f} {unit}"


def suite_standing(report: dict[str, Any]) -> tuple[str, int, int]:
    """Markdown: one line per target (``*`` targets: one per condition), value, met; and the
    counts (met, total)."""
    lines = ["| target | value | met |", "|---|---:|:---:|"]
    met = total = 0
    for t in SUITE_TARGETS:
        names = list(report["conditions"]) if t.condition == "*" else [t.condition]
        for name in names:
            v = t.value(report, name)
            ok = t.met(v)
            met += ok
            total += 1
            lines.append(
                f"| {t.describe(name)} | {_fmt(v, t.unit)} | {'yes' if ok else '**no**'} |"
            )
    return "\n".join(lines), met, total


def _cell(r: dict[str, Any] | None) -> list[str]:
    if r is None:
        return ["—", "—", "—", "—"]
    e = r.get("landing_error_m") or {}
    v = r.get("touchdown_speed_m_s") or {}
    return [
        f"{100 * r['success_rate']:.1f} % ({r['episodes']})",
        _fmt(e.get("mean"), "m"),
        _fmt(e.get("max"), "m"),
        _fmt(v.get("mean"), "m/s"),
    ]


def suite_comparison(
    report: dict[str, Any], baseline: dict[str, Any] | None, names: tuple[str, str]
) -> str:
    """Markdown: per condition, success (episodes), mean and max error and mean touchdown
    speed of ``report``'s policy beside ``baseline``'s (None: that column is left out)."""
    head = ["condition", *(f"{names[0]}: {h}" for h in ("success", "mean", "max", "touchdown"))]
    if baseline is not None:
        head += [f"{names[1]}: {h}" for h in ("success", "mean", "max", "touchdown")]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for name, r in report["conditions"].items():
        cells = [name, *_cell(r)]
        if baseline is not None:
            cells += _cell(baseline["conditions"].get(name))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
