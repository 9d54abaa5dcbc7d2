"""The robust policy's acceptance on the benchmark suite: issue 16's targets per condition, and
the suite table of a policy beside a baseline's (the paper-world model), as markdown for
``docs/results.md`` and the model card. Every number is read from ``run_suite`` reports
(:class:`~training.reports.SuiteReport`)."""

from __future__ import annotations

from training.report.targets import SUITE_TARGETS, standing, value_text
from training.reports import EvalReport, SuiteReport

__all__ = ["suite_comparison", "suite_standing"]


def suite_standing(report: SuiteReport) -> tuple[str, int, int]:
    """Markdown: one line per target of :data:`~training.report.targets.SUITE_TARGETS` (``*``
    targets: one per condition), value, met; and the counts (met, total)."""
    table, met, _ = standing(SUITE_TARGETS, report.conditions, every=report.conditions)
    return table, sum(met), len(met)


def _cell(r: EvalReport | None) -> list[str]:
    if r is None:
        return ["—", "—", "—", "—"]
    s = r.summary
    return [
        f"{100 * s.success_rate:.1f} % ({r.episodes})",
        value_text(s.landing_error_m.mean, "m"),
        value_text(s.landing_error_m.max, "m"),
        value_text(s.touchdown_speed_m_s.mean, "m/s"),
    ]


def suite_comparison(
    report: SuiteReport, baseline: SuiteReport | None, names: tuple[str, str]
) -> str:
    """Markdown: per condition, success (episodes), mean and max error and mean touchdown
    speed of ``report``'s policy beside ``baseline``'s (None: that column is left out)."""
    head = ["condition", *(f"{names[0]}: {h}" for h in ("success", "mean", "max", "touchdown"))]
    if baseline is not None:
        head += [f"{names[1]}: {h}" for h in ("success", "mean", "max", "touchdown")]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for name, r in report.conditions.items():
        cells = [name, *_cell(r)]
        if baseline is not None:
            cells += _cell(baseline.conditions.get(name))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
