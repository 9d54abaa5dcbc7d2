"""``visland eval --suite FILE``: a benchmark suite — named conditions, each a complete scenario,
flown by the same :func:`training.evaluate.evaluate` as ``visland eval``.

A suite file (TOML, e.g. ``configs/suites/standard.toml``)::

    [suite]                      # optional; both keys optional
    episodes = 50                # per condition (``--episodes`` overrides)
    seed = 1000000               # evaluation seed (``--seed`` overrides)

    [conditions.nominal]
    scenario = "configs/scenario.toml"   # a scenario file: relative to the repository root
    episodes = 300                       # optional: this condition's own count

    [conditions.windy.scenario.initial_state]   # or inline: the sections of a scenario file
    roll_pitch_deg = [-1.5, 1.5]
    ...
    [conditions.windy.scenario.wind]
    ...

An inline scenario is checked by the code that checks scenario files
(:func:`sitl_sim.scenario.scenario_from_dict`); its errors name ``<suite file>:
[conditions.<name>]``. Conditions fly one after another, in file order, each over the worker
processes; every condition uses the same seed, so episode ``i`` starts from the same sample of
its scenario's ranges as episode ``i`` of ``visland eval --scenario ... --seed ...``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar, TextIO

from companion.table import Section, integer
from sitl_sim.config import load_toml
from sitl_sim.errors import ConfigError
from sitl_sim.scenario import Scenario, load_scenario, scenario_from_dict
from training.evaluate import EvalConfig, evaluate
from training.provenance import REPO
from training.reports import EvalReport, SuiteReport
from training.seeds import EVAL_SEED

__all__ = [
    "Condition",
    "SuiteConfig",
    "SuiteSection",
    "format_suite_table",
    "load_suite",
    "plot_suite",
    "run_suite",
    "scenario_file",
]

DEFAULT_EPISODES = 50

_TOP_LEVEL = ("suite", "conditions")
_CONDITION_KEYS = ("scenario", "episodes")


@dataclass(frozen=True)
class Condition:
    """One named condition: its checked scenario and where it came from."""

    name: str
    scenario: Scenario
    file: str | None = None
    """The scenario file as written in the suite (None: an inline table)."""
    episodes: int | None = None
    """This condition's episode count (None: the suite's)."""


@dataclass(frozen=True)
class SuiteConfig:
    """A loaded suite file: episodes and seed per condition, the conditions in file order."""

    path: str
    episodes: int
    seed: int
    conditions: tuple[Condition, ...]


@dataclass(frozen=True)
class SuiteSection(Section):
    """A suite file's optional ``[suite]`` table (read by :mod:`companion.table`)."""

    SECTION: ClassVar[str] = "suite"

    episodes: int = integer(
        DEFAULT_EPISODES, unit="episodes", lo=1, doc="per condition (--episodes overrides)"
    )
    seed: int = integer(EVAL_SEED, unit="1", lo=0, doc="evaluation seed (--seed overrides)")


def _unknown(where: str, table: str, got: Mapping[str, Any], expected: tuple[str, ...]) -> None:
    unknown = sorted(set(got) - set(expected))
    if unknown:
        raise ConfigError(
            f"{where}: {table} unknown key(s) {unknown}; expected {list(expected)} (typo?)"
        )


def _resolve(file: str) -> Path:
    path = Path(file)
    return path if path.is_absolute() else REPO / path


def _condition(where: str, name: str, table: Any) -> Condition:
    tag = f"[conditions.{name}]"
    if not isinstance(table, dict):
        raise ConfigError(
            f'{where}: {tag} must be a table with scenario = "FILE" or a [conditions.{name}'
            f".scenario] table, got {table!r}"
        )
    _unknown(where, tag, table, _CONDITION_KEYS)
    if "scenario" not in table:
        raise ConfigError(
            f'{where}: {tag} has no scenario; expected scenario = "FILE" (relative to the '
            f"repository root) or an inline [conditions.{name}.scenario] table with the sections "
            "of a scenario file"
        )
    value = table["scenario"]
    n = table.get("episodes")
    if n is not None and (not isinstance(n, int) or isinstance(n, bool) or n < 1):
        raise ConfigError(f"{where}: {tag} episodes = {n!r}; expected an integer >= 1")
    if isinstance(value, str):
        return Condition(
            name=name, scenario=scenario_file(where, tag, value), file=value, episodes=n
        )
    if isinstance(value, dict):
        return Condition(
            name=name, scenario=scenario_from_dict(value, f"{where}: {tag}"), episodes=n
        )
    raise ConfigError(
        f"{where}: {tag} scenario = {value!r}; expected a file path (string) or a table of "
        "scenario sections"
    )


def scenario_file(where: str, tag: str, value: str) -> Scenario:
    """The checked scenario of ``scenario = "FILE"`` in table ``tag`` of file ``where`` (a path
    relative to the repository root, or absolute)."""
    path = _resolve(value)
    if not path.is_file():
        raise ConfigError(f"{where}: {tag} scenario = {value!r}: file not found ({path})")
    return load_scenario(path)


def load_suite(path: str | Path) -> SuiteConfig:
    """Read and check a suite file; every condition's scenario is loaded and checked now, so a
    bad condition fails before any episode flies."""
    where = str(path)
    data = load_toml(path)
    _unknown(where, "top level", data, _TOP_LEVEL)
    head = SuiteSection.from_table(data.get("suite", {}), where)
    conditions = data.get("conditions")
    if not isinstance(conditions, dict) or not conditions:
        raise ConfigError(f"{where}: no [conditions.NAME] tables; expected at least one condition")
    return SuiteConfig(
        path=where,
        episodes=head.episodes,
        seed=head.seed,
        conditions=tuple(_condition(where, n, t) for n, t in conditions.items()),
    )


def run_suite(
    suite: SuiteConfig,
    flying: EvalConfig,
    *,
    episodes: int | None = None,
    seed: int | None = None,
) -> SuiteReport:
    """Fly every condition with :func:`evaluate`, one after another, each as ``flying`` says
    (the policy, workers or backend, camera, kept logs, estimator settings) with the
    condition's scenario, episodes and seed and its name on the kept logs. ``episodes``/``seed``
    override the suite file's (``episodes`` every condition's, its own count included)."""
    n = suite.episodes if episodes is None else episodes
    s = suite.seed if seed is None else seed
    reports: dict[str, EvalReport] = {}
    for k, cond in enumerate(suite.conditions, 1):
        if flying.progress:
            print(f"condition {k}/{len(suite.conditions)}: {cond.name}", file=sys.stderr)
        reports[cond.name] = evaluate(
            replace(
                flying,
                episodes=cond.episodes if episodes is None and cond.episodes else n,
                seed=s,
                scenario=cond.scenario,
                condition=cond.name,
            )
        )
    return SuiteReport(
        suite=suite.path, policy=flying.policy, seed=s, episodes=n, conditions=reports
    )


def _nan_for_none(value: float | None) -> float:
    """A statistic as a number: NaN for none (a report read back from JSON has null)."""
    return math.nan if value is None else value


def _num(value: float | None, width: int, digits: int) -> str:
    value = _nan_for_none(value)
    return f"{'-':>{width}}" if math.isnan(value) else f"{value:{width}.{digits}f}"


def _cells(r: EvalReport, widths: tuple[int, int, int] = (0, 0, 0)) -> list[str]:
    """A condition's landing error mean and max and touchdown speed mean, each as wide as
    ``widths`` says ("-": no episode touched down)."""
    s = r.summary
    values = (s.landing_error_m.mean, s.landing_error_m.max, s.touchdown_speed_m_s.mean)
    return [_num(v, w, 3) for v, w in zip(values, widths, strict=True)]


def _on_pad(r: EvalReport) -> tuple[int, int] | None:
    """(touchdowns on the pad's own surface, touchdowns) of a condition flown on a site; None
    for one on the nominal site (its rows carry no ``touched_pad``)."""
    rows = [row for row in r.per_episode if row.landed]
    if not any(row.touched_pad is not None for row in r.per_episode):
        return None
    return sum(bool(row.touched_pad) for row in rows), len(rows)


def _unsafe(r: EvalReport) -> tuple[str, str]:
    """A condition's off-pad touchdowns (the unsafe failures) and aborts, as table cells ("-"
    in a report written before they were counted)."""
    s = r.summary
    return tuple("-" if v is None else str(v) for v in (s.off_pad, s.aborts))  # type: ignore[return-value]


def format_suite_table(report: SuiteReport, out: TextIO) -> None:
    """One row per condition: episodes, success, landing error mean/max, touchdown speed mean
    ("-": no episode touched down), off-pad touchdowns, aborts, timeouts."""
    conds = report.conditions
    width = max([len("condition"), *(len(n) for n in conds)])
    out.write(
        f"{report.policy}: suite {report.suite}, {report.episodes} episodes per "
        f"condition, seed {report.seed}\n"
    )
    out.write(
        f"  {'condition':<{width}}  episodes  success %  error mean m  error max m"
        "  touchdown mean m/s  off pad  aborts  timeouts\n"
    )
    for name, r in conds.items():
        mean, worst, touchdown = _cells(r, (12, 11, 18))
        off_pad, aborts = _unsafe(r)
        out.write(
            f"  {name:<{width}}  {r.episodes:8d}  {100 * r.summary.success_rate:9.1f}"
            f"  {mean}  {worst}  {touchdown}  {off_pad:>7}  {aborts:>6}"
            f"  {r.summary.timeouts:8d}\n"
        )
    kept = [(name, row) for name, r in conds.items() for row in r.per_episode if row.log]
    if kept:
        out.write(f"  flight logs kept ({len(kept)}):\n")
        for name, row in kept:
            out.write(
                f"    {name:<{width}}  episode {row.episode:4d}  {row.verdict():<13} {row.log}\n"
            )


def suite_markdown(report: SuiteReport, command: str, plot: str | None = None) -> str:
    """A results page for docs/: what was run (command, commit, date), one table row per
    condition and the plot — written by ``visland eval --suite ... --markdown FILE``, never by
    hand."""
    from datetime import UTC, datetime

    from training.provenance import git_commit

    lines = [
        f"# Benchmark suite: {report.policy} on `{report.suite}`",
        "",
        "Generated by a command; do not edit (run it again instead):",
        "",
        "```",
        command,
        "```",
        "",
        f"Commit `{git_commit()}`, {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}; "
        f"{report.episodes} episodes per condition (the table says where a condition has "
        f"its own count), evaluation seed {report.seed} "
        "(disjoint from every training and selection seed). Success: touched down within "
        "the pad's success radius, upright and slow (training/evaluate.py). *Off pad*: "
        "touchdowns more than 2 m from the pad — the unsafe failures; *aborts*: flights the "
        "policy ended in the air because it found no pad (a failure, not a touchdown; "
        "companion/policy_net/guard.py).",
        "",
    ]
    sites = any(_on_pad(r) is not None for r in report.conditions.values())
    if sites:
        lines.append(
            "On a site (a moving pad, a slope, rocks) the metrics are in the pad's frame and "
            "*on pad %* is the share of touchdowns on the pad's own surface; *not on pad* "
            "counts touchdowns elsewhere (the ground beside a rover, the sea, a rock)."
        )
        lines.append("")
    extra = " on pad % | not on pad |" if sites else ""
    lines += [
        "| condition | episodes | success % | error mean m | error max m "
        f"| touchdown mean m/s | off pad | aborts | timeouts |{extra}",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|" if sites else ""),
    ]
    for name, r in report.conditions.items():
        mean, worst, touchdown = _cells(r)
        off_pad, aborts = _unsafe(r)
        row = (
            f"| {name} | {r.episodes} | {100 * r.summary.success_rate:.1f} "
            f"| {mean} | {worst} | {touchdown} | {off_pad} | {aborts} | {r.summary.timeouts} |"
        )
        if sites:
            counts = _on_pad(r)
            if counts is None:
                row += " - | - |"
            else:
                on, landed = counts
                share = f"{100 * on / landed:.1f}" if landed else "-"
                row += f" {share} | {landed - on} |"
        lines.append(row)
    if plot:
        lines += ["", f"![success and mean landing error per condition]({plot})"]
    return "\n".join(lines) + "\n"


def plot_suite(report: SuiteReport, out_png: str | Path) -> Path:
    """Two bar panels side by side: success rate and mean landing error per condition (PNG,
    matplotlib Agg)."""
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window
    import matplotlib.pyplot as plt

    names = list(report.conditions)
    summaries = [r.summary for r in report.conditions.values()]
    success = [100 * s.success_rate for s in summaries]
    error = [_nan_for_none(s.landing_error_m.mean) for s in summaries]
    x = list(range(len(names)))
    fig, (ax_s, ax_e) = plt.subplots(1, 2, figsize=(max(8.0, 1.6 * len(names) + 4), 4.2))
    ax_s.bar(x, success, color="tab:green")
    ax_s.set_ylim(0, 105)
    ax_s.set_ylabel("success rate (%)")
    ax_e.bar(x, [0.0 if math.isnan(e) else e for e in error], color="tab:blue")
    ax_e.set_ylabel("mean landing error (m)")
    for ax in (ax_s, ax_e):
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=25, ha="right")
        ax.grid(axis="y", alpha=0.3)
    for i, e in enumerate(error):
        if math.isnan(e):
            ax_e.text(i, 0.0, "no touchdown", ha="center", va="bottom", fontsize=7)
    fig.suptitle(
        f"{report.policy} — {report.suite}: {report.episodes} episodes per "
        f"condition, seed {report.seed}",
        fontsize=9,
    )
    fig.tight_layout()
    path = Path(out_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80, pil_kwargs={"optimize": True})
    plt.close(fig)
    return path
