"""``visland report``: ``docs/results.md`` and its figures, generated from a run's ``metrics.json``.

Every number in the report is read from the run (``<run>/metrics.json``, written by the
pipeline's eval stage; ``<run>/scalars.jsonl`` for the loss curves) or computed from it here; the
only numbers typed by hand are the paper's own (``training.paper``, cited by section) and the
project's targets (``training.report.markdown.TARGETS``). The
trajectory figures (the kind of the paper's Figures 3-11) come from flying one evaluation episode
in process with each of the run's four policies — the same seed and episode index the eval stage
flew, so each flight is checked against its ``per_episode`` row (lockstep flights are
deterministic). Each figure carries the command and the commits that made it in a footer, and
each caption in the markdown says the same.

The landing scatter needs ``per_episode[*].touchdown_ne_m`` (recorded by
``training.exec.rollout.fly_episode`` since it was added); for a run evaluated before that, the
report says the scatter is unavailable and which command regenerates the eval stage — it never
guesses positions.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from training.profiles import LABEL_KEYS
from training.report.figures import (
    FIGURE_PATTERNS,
    SCATTER_VIEW_M,
    default_episodes,
    fly_traces,
    loss_series,
    plot_hist,
    plot_inputs,
    plot_loss,
    plot_scatter,
    plot_states,
    scenario_of,
    touchdowns,
)
from training.report.markdown import (
    header,
    regenerate_eval,
    rollouts_text,
    runtime,
    standing,
    table3,
    trajectory_caption,
)
from training.report.metrics import Provenance, ReportError, code_commit, load_metrics
from training.report.targets import fmt, pct
from training.reports import EvalReport, SuiteReport
from training.stage_records import Metrics

__all__ = [
    "ReportConfig",
    "ReportError",
    "ReportResult",
    "load_metrics",
    "rollouts_text",
    "write_report",
]


@dataclass(frozen=True)
class ReportConfig:
    """Options of ``visland report``."""

    run: Path
    """Run folder with ``metrics.json`` (``visland pipeline --out RUN``)."""
    out: Path = Path("docs/results.md")
    """The markdown file to write."""
    figures_dir: Path | None = None
    """Where the PNGs go (default: ``figures/`` beside ``out``)."""
    trajectories: bool = True
    """Fly the trajectory episodes in process (four policies; ``False`` skips those figures)."""
    trajectory_episodes: tuple[int, ...] | None = None
    """Eval episode indices to fly (default: episode 0 and the vision row's worst episode)."""
    ablations: tuple[Path, ...] = ()
    """Other run folders whose eval stage flew the same suite (one profile key changed): their
    suite results go beside the run's."""

    def figures(self) -> Path:
        return Path(self.figures_dir) if self.figures_dir else Path(self.out).parent / "figures"

    def command(self) -> str:
        """The ``visland report`` command line that reproduces this report."""
        parts = ["visland report", f"--run {self.run}"]
        if Path(self.out) != Path("docs/results.md"):
            parts.append(f"--out {self.out}")
        if self.figures_dir is not None and self.figures() != Path(self.out).parent / "figures":
            parts.append(f"--figures-dir {self.figures_dir}")
        if not self.trajectories:
            parts.append("--no-trajectories")
        parts += [f"--ablation {a}" for a in self.ablations]
        return " ".join(parts)


@dataclass(frozen=True)
class ReportResult:
    """What :func:`write_report` wrote and how the run stands against :data:`TARGETS`."""

    out: Path
    figures: tuple[Path, ...]
    targets_met: tuple[bool, ...]
    standing: str
    notes: tuple[str, ...] = field(default_factory=tuple)


# ------------------------------------------------------------------------------ writing it


class _Figures:
    """The report's figures in order: each PNG, and its markdown (image link + numbered caption)."""

    def __init__(self, out: Path, prov: Provenance) -> None:
        self._base = out.parent
        self._prov = prov
        self.paths: list[Path] = []
        self.sections: list[str] = []

    def add(self, path: Path, alt: str, caption: str) -> None:
        self.paths.append(path)
        link = Path(os.path.relpath(path, self._base)).as_posix()
        self.sections.append(
            f"![{alt}]({link})\n\n*Figure {len(self.paths)}: {caption} {self._prov.caption()}*"
        )

    def say(self, text: str) -> None:
        self.sections.append(text)


def _add_trajectories(
    figs: _Figures,
    metrics: Metrics,
    run: Path,
    episodes: tuple[int, ...],
    figdir: Path,
    prov: Provenance,
) -> list[str]:
    """Fly ``episodes`` with the four policies, draw states and inputs; returns the flights
    that do not reproduce their eval record."""
    scenario = scenario_of(metrics, run / "metrics.json")
    seed = metrics.eval_seed
    worst = default_episodes(metrics)[-1]
    mismatches: list[str] = []
    for ep in episodes:
        traces = fly_traces(metrics, run, ep, scenario)
        which = f"eval episode {ep}" + (
            " (the vision row's worst)" if ep == worst and ep != episodes[0] else ""
        )
        v = traces["vision"]
        title = (
            f"Seed {seed}, {which}; vision landing error {fmt(v.landing_error_m)} m flown now, "
            f"{fmt(v.eval_error_m)} m in metrics.json"
        )
        mismatches += [
            f"{row} episode {ep} ({fmt(t.landing_error_m)} m now, {fmt(t.eval_error_m)} m in "
            "metrics.json)"
            for row, t in traces.items()
            if t.eval_error_m is not None and abs(t.eval_error_m - t.landing_error_m) > 1e-6
        ]
        figs.add(
            plot_states(traces, title, figdir / f"trajectory_states_ep{ep}.png", prov),
            f"states, episode {ep}",
            "state trajectories (ground-truth NED position, velocity, roll/pitch/yaw at each "
            f"10 Hz control step) of {which}, flown in process by all four policies — the "
            "paper's Figures 3 (expert), 6 (vision), 8 (BC) and 10 (DAgger) show this for many "
            "episodes. " + trajectory_caption(traces, seed, ep),
        )
        figs.add(
            plot_inputs(traces, title, figdir / f"trajectory_inputs_ep{ep}.png", prov),
            f"inputs, episode {ep}",
            "the inputs (Command: collective thrust_norm and FRD body rates) of the same flights "
            "— the paper's Figures 4, 7, 9 and 11 (its inputs are thrust and body torques; ours "
            "are the autopilot's rate setpoints).",
        )
    return mismatches


def _started_from(run: Path) -> str | None:
    """The run whose trained stages ``run`` took (``profile.json`` ``started_from``), if any."""
    try:
        data = json.loads((run / "profile.json").read_text())
    except (OSError, ValueError):
        return None
    start = data.get("started_from") if isinstance(data, dict) else None
    return str(start["run"]) if isinstance(start, dict) and "run" in start else None


def ablation_section(metrics: Metrics, runs: tuple[Path, ...]) -> str:
    """Per suite condition, the run's success and mean error beside each ablation run's (the
    profile keys it changed named in its column); empty without ablations or a suite."""
    if not runs or not metrics.suite:
        return ""
    ours = SuiteReport.load(metrics.suite)
    mine = metrics.profile.to_dict()
    columns = []
    for run in runs:
        other = load_metrics(Path(run))
        if not other.suite:
            raise ReportError(f"{run}/metrics.json: no suite results (its profile flies none)")
        theirs = other.profile.to_dict()
        changed = [
            f"{k}={theirs[k]}" for k in mine if k not in LABEL_KEYS and theirs.get(k) != mine[k]
        ]
        start = _started_from(Path(run))
        if start:
            changed.append(f"the networks of {start}")
        columns.append((f"{run}: {', '.join(changed) or 'same profile'}", other))
    head = ["condition", f"{metrics.profile.name} (shipped)"] + [c[0] for c in columns]
    lines = [
        "### Ablations on the suite",
        "",
        "Each cell: success and mean landing error; the same suite and seeds, each run trained "
        "from scratch by its profile (`visland pipeline --profile P`) unless its column names "
        "the networks it took (`visland pipeline --profile P --from RUN`: the same networks, "
        "another estimator).",
        "",
        "| " + " | ".join(head) + " |",
        "|---|" + "---:|" * (len(head) - 1),
    ]
    reports = [SuiteReport.load(o.suite) for _, o in columns]

    def cell(r: EvalReport | None) -> str:
        if r is None:
            return "—"
        return f"{pct(r.summary.success_rate)}, {fmt(r.summary.landing_error_m.mean)} m"

    for name, r in ours.conditions.items():
        cells = [name, cell(r)] + [cell(rep.conditions.get(name)) for rep in reports]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n"


def suite_section(metrics: Metrics) -> str:
    """The benchmark suite beside the baseline's, issue 16's targets and the vision stage's
    validation of its candidates (what the DAgger rounds bought), when the eval stage flew the
    profile's suite; empty otherwise."""
    if not metrics.suite:
        return ""
    from training.report.suite import suite_comparison, suite_standing

    report = SuiteReport.load(metrics.suite)
    baseline = SuiteReport.load(metrics.suite_baseline) if metrics.suite_baseline else None
    ours = Path(metrics.stages.vision.checkpoint).name if metrics.stages.vision else "vision"
    base = Path(baseline.policy).name if baseline else ""
    standing_md, met, total = suite_standing(report)
    lines = [
        f"## Benchmark suite — `{metrics.profile.eval_suite or report.suite}`, seed {report.seed}",
        "",
        f"The run's vision policy (`{ours}`)"
        + (
            f" beside the paper-world model (`{base}`, the baseline: no domain randomisation, "
            "no hover input), flown on the same episodes."
            if baseline
            else "."
        ),
        "Each cell: success (episodes), mean and max landing error, mean touchdown speed.",
        "",
        suite_comparison(report, baseline, (ours, base)),
        "",
        f"### Issue 16's targets: {met} of {total} met",
        "",
        standing_md,
        "",
    ]
    vision = metrics.stages.vision
    if vision is not None and vision.validation:
        lines += [
            "### Ablation: what each vision candidate scored on validation",
            "",
            "Validation episodes (seed "
            f"{metrics.profile.validation_seed}, pooled over the training worlds) of every "
            "candidate the vision stage made: the privileged controllers fed by CNN + estimator "
            "(`vision_prior_*`), vision BC on the expert's flights, and each vision DAgger round "
            "— what the rounds bought. The lowest score is shipped.",
            "",
            "| candidate | score | success | mean error (m) | touchdown mean (m/s) |",
            "|---|---:|---:|---:|---:|",
        ]
        for v in vision.validation:
            lines.append(
                f"| {Path(v.checkpoint).stem} | {v.score:.3f} | {pct(v.success_rate)} "
                f"| {fmt(v.mean_error_m)} | {fmt(v.touchdown_speed_mean_m_s)} |"
            )
        lines.append("")
    return "\n".join(lines) + "\n"


def write_report(cfg: ReportConfig) -> ReportResult:
    """Write ``cfg.out`` and its figures from ``<cfg.run>/metrics.json``; see the module doc.

    Raises:
        ReportError: the run folder, ``metrics.json`` or a field of it is missing or malformed,
            or a checkpoint or scenario needed for the trajectory flights is gone.
    """
    run = Path(cfg.run)
    metrics = load_metrics(run)
    mpath = run / "metrics.json"
    out = Path(cfg.out)
    figdir = cfg.figures()
    prov = Provenance(cfg.command(), code_commit(), run, metrics.git_commit or "unknown")
    episodes = tuple(dict.fromkeys(cfg.trajectory_episodes or default_episodes(metrics)))
    if any(e < 0 for e in episodes):
        raise ReportError(f"trajectory episodes must be >= 0, got {episodes}")
    if cfg.trajectories:
        scenario_of(metrics, mpath)  # fail before any file is touched

    figdir.mkdir(parents=True, exist_ok=True)
    for pattern in FIGURE_PATTERNS:  # a figure this report no longer makes must not linger
        for old in figdir.glob(pattern):
            old.unlink()
    figs = _Figures(out, prov)
    notes: list[str] = []

    mismatches = None
    if cfg.trajectories:
        mismatches = _add_trajectories(figs, metrics, run, episodes, figdir, prov)
    else:
        figs.say(
            "Trajectory figures were skipped (`--no-trajectories`); run "
            f"`visland report --run {run}` to fly and draw them."
        )

    touch = touchdowns(metrics)
    if sum(len(ne) for ne, _, _ in touch.values()) == 0:
        note = (
            f"**Landing scatter unavailable for this run**: `{mpath}` has no "
            "`per_episode[*].touchdown_ne_m` (the run was evaluated before touchdown positions "
            f"were recorded). Regenerate the eval stage with `{regenerate_eval(run, metrics)}`, "
            f"then rerun `{cfg.command()}`."
        )
        notes.append(note)
        figs.say(note)
    else:
        lacking = sum(k for _, _, k in touch.values())
        figs.add(
            plot_scatter(metrics, figdir / "landing_scatter.png", prov),
            "landing scatter",
            "touchdown positions (east, north) around the pad of every eval episode, per policy; "
            f"green = success, red = failure; ▲ on the border = beyond ±{SCATTER_VIEW_M:g} m, "
            "in its direction."
            + (f" {lacking} episodes have no recorded position, not drawn." if lacking else ""),
        )

    figs.add(
        plot_hist(metrics, figdir / "landing_error_hist.png", prov),
        "landing error histogram",
        "landing error of every eval episode, log-spaced bins; dotted lines = the paper's "
        "Table 3 means.",
    )
    loss = plot_loss(loss_series(run), figdir / "training_loss.png", prov)
    if loss is not None:
        figs.add(
            loss,
            "training loss",
            f"controller training loss from `{run}/scalars.jsonl`; dotted lines mark where "
            "learner rollouts, relabelled by the expert, were aggregated (the paper's Figure 5).",
        )

    stand, met = standing(metrics)
    suite_md = suite_section(metrics) + ablation_section(metrics, cfg.ablations)
    md = (
        f"""{header(cfg.command(), metrics, prov, mismatches)}
## Where we stand

{stand}

{suite_md}## Table 3 — landing performance, ours beside the paper (paper §5.4)

{table3(metrics)}

The paper's Table 3 has landing error only and no expert row; its LSTM-only rows are
privileged (true position and velocity), as ours are. Numbers: {prov.caption()}

## Runtime — MPC vs policy per control step (paper §6)

{runtime(metrics, mpath)}

## Figures

"""
        + "\n\n".join(figs.sections)
        + "\n"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(md)
    return ReportResult(
        out=out,
        figures=tuple(figs.paths),
        targets_met=met,
        standing=stand.split("\n", 1)[0],
        notes=tuple(notes),
    )
