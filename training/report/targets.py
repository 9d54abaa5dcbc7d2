"""The acceptance targets a report checks, and how it writes a number.

One :class:`Target` for both tables the project is judged by: the paper-world Table 3 rows of
``metrics.json`` (:data:`TARGETS`, read from the typed ``Rows``) and the conditions of the
standard benchmark suite (:data:`SUITE_TARGETS`, read from a ``run_suite`` report's
``conditions``): each an :class:`~training.reports.EvalReport`, its ``summary`` checked.
:func:`standing` is the one ``| target | value | met |`` table of both.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from training.reports import EvalReport
    from training.stage_records import Rows

__all__ = ["SUITE_TARGETS", "TARGETS", "Target", "fmt", "pct", "standing", "value_text"]


def fmt(v: Any, digits: int = 3) -> str:
    """A number as the report writes it: ``n/a`` for none or not finite, ``1.2e-05`` for one
    too small for ``digits`` decimals."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if v != 0 and abs(v) < 10 ** (-digits):
        return f"{v:.1e}"
    return f"{v:.{digits}f}"


def pct(v: Any) -> str:
    """A rate in [0, 1] as a percentage (``n/a`` for none)."""
    return "n/a" if v is None else f"{100 * v:.1f} %"


def value_text(v: float | None, unit: str) -> str:
    """A target's value with its unit (``%``: a rate), ``n/a`` for none or not finite."""
    if v is None or not math.isfinite(v):
        return "n/a"
    return pct(v) if unit == "%" else f"{fmt(v)} {unit}"


def _report(table: Rows | Mapping[str, EvalReport], condition: str) -> EvalReport | None:
    """The report of ``condition`` (a Table 3 row, a suite condition); None if absent."""
    if isinstance(table, Mapping):
        return table.get(condition)
    return getattr(table, condition, None)


_WHAT = {"success_rate": "success", "landing_error_m": "error"}


@dataclass(frozen=True)
class Target:
    """``table[condition][metric][stat] <op> limit`` (``stat`` None: a scalar).

    ``table`` is what the target is checked against: a suite report's ``conditions`` (then
    ``condition`` is a suite condition, ``*`` each of them) or ``metrics.json``'s ``Rows``
    (then ``condition`` is a Table 3 row, the policy flown in the paper's world).
    """

    condition: str
    metric: str
    stat: str | None
    op: str
    limit: float
    unit: str

    def describe(self, label: str | None = None) -> str:
        """``<label>: <what> ≤ <limit>`` (``label``: default the condition)."""
        if self.metric == "touchdown_speed_m_s":
            what = f"touchdown speed {self.stat}"
        else:
            what = _WHAT.get(self.metric, self.metric) + (f" {self.stat}" if self.stat else "")
        limit = f"{100 * self.limit:g} %" if self.unit == "%" else f"{self.limit:g} {self.unit}"
        return f"{label or self.condition}: {what} {'≤' if self.op == '<=' else '≥'} {limit}"

    def value(
        self, table: Rows | Mapping[str, EvalReport], condition: str | None = None
    ) -> float | None:
        """The value in ``table`` (of ``condition``, default this target's); None if absent."""
        report = _report(table, condition or self.condition)
        if report is None:
            return None
        v = getattr(report.summary, self.metric)
        if self.stat is not None:
            v = getattr(v, self.stat)
        return None if v is None else float(v)

    def met(self, table: Rows | Mapping[str, EvalReport], condition: str | None = None) -> bool:
        """Whether the value in ``table`` meets the target (an absent or NaN value does not)."""
        v = self.value(table, condition)
        if v is None or not math.isfinite(v):
            return False
        return v <= self.limit if self.op == "<=" else v >= self.limit


TARGETS: tuple[Target, ...] = (
    Target("dagger", "landing_error_m", "mean", "<=", 0.30, "m"),
    Target("vision", "landing_error_m", "mean", "<=", 0.50, "m"),
    Target("vision", "landing_error_m", "max", "<=", 1.2, "m"),
    Target("vision", "touchdown_speed_m_s", "mean", "<=", 1.0, "m/s"),
    Target("vision", "success_rate", None, ">=", 0.95, "%"),
)
"""The project's targets for the Table 3 rows (the issue's acceptance figures)."""

SUITE_TARGETS: tuple[Target, ...] = (
    Target("nominal", "landing_error_m", "mean", "<=", 0.15, "m"),
    Target("nominal", "landing_error_m", "max", "<=", 0.5, "m"),
    Target("nominal", "success_rate", None, ">=", 0.997, "%"),
    Target("mars", "success_rate", None, ">=", 0.99, "%"),
    Target("mars", "landing_error_m", "mean", "<=", 0.3, "m"),
    Target("wind_moderate_gusts", "success_rate", None, ">=", 0.98, "%"),
    Target("wind_moderate_gusts", "landing_error_m", "mean", "<=", 0.4, "m"),
    Target("unseen_terrain", "success_rate", None, ">=", 0.98, "%"),
    Target("unseen_terrain", "landing_error_m", "mean", "<=", 0.4, "m"),
    Target("low_sun", "success_rate", None, ">=", 0.98, "%"),
    Target("low_sun", "landing_error_m", "mean", "<=", 0.4, "m"),
    Target("sensor_latency_dropouts", "success_rate", None, ">=", 0.98, "%"),
    Target("heavy_vehicle", "success_rate", None, ">=", 0.98, "%"),
    Target("light_vehicle", "success_rate", None, ">=", 0.98, "%"),
    Target("*", "touchdown_speed_m_s", "mean", "<=", 0.6, "m/s"),
)
"""Issue 16's acceptance table for the vision policy on ``configs/suites/standard.toml``."""


def standing(
    targets: Iterable[Target],
    table: Rows | Mapping[str, EvalReport],
    every: Iterable[str] = (),
    label: Callable[[str], str] = str,
) -> tuple[str, list[bool], list[str]]:
    """Markdown ``| target | value | met |``, one line per target and condition (a ``*``
    target: one per condition of ``every``); the met flags in that order; the descriptions of
    those not met. ``label(condition)`` names a condition in the descriptions."""
    lines = ["| target | value | met |", "|---|---:|:---:|"]
    met: list[bool] = []
    missed: list[str] = []
    for t in targets:
        for name in list(every) if t.condition == "*" else [t.condition]:
            ok = t.met(table, name)
            met.append(ok)
            described = t.describe(label(name))
            if not ok:
                missed.append(described)
            shown = value_text(t.value(table, name), t.unit)
            lines.append(f"| {described} | {shown} | {'yes' if ok else '**no**'} |")
    return "\n".join(lines), met, missed
