"""The report's markdown: where the run stands against the project's targets, Table 3 beside
the paper's, the runtime comparison, the header with seeds and commits, figure captions."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Any

from training.exec.transport import Transport
from training.paper import PAPER_RUNTIME_S, PAPER_TABLE3, PAPER_VISION_TERMINAL_SPEED_M_S
from training.report.figures import Trace
from training.report.metrics import ROWS, Provenance, short
from training.report.targets import TARGETS, fmt, pct
from training.report.targets import standing as targets_standing
from training.stage_records import Metrics

__all__ = [
    "header",
    "regenerate_eval",
    "rollouts_text",
    "runtime",
    "standing",
    "table3",
    "trajectory_caption",
]


# ------------------------------------------------------------------------------ markdown


def _seed_line(metrics: Metrics) -> str:
    p = metrics.profile
    ev, n = metrics.eval_seed, metrics.episodes
    used: dict[str, list[int]] = {
        "expert collection": [p.collect_seed],
        "dagger rollouts": [p.dagger_seed + k for k in range(max(1, p.dagger_rounds or 1))],
        "vision rollouts": [p.vision_seed + k for k in range(max(1, p.vision_rounds or 1))],
        "validation": [p.validation_seed],
    }
    clash = sorted({k for k, seeds in used.items() if ev in seeds})
    listing = "; ".join(f"{k} {', '.join(map(str, v))}" for k, v in used.items())
    verdict = (
        "**not disjoint** — the evaluation seed was also used for " + ", ".join(clash)
        if clash
        else "disjoint from every seed used in training and model selection"
    )
    return (
        f"Evaluation: {n} episodes per row, seed {ev} (episode indices 0–{n - 1}); seeds used "
        f"before it ({listing}) — the evaluation seed is {verdict}. An episode's initial state "
        "is a function of (seed, index) only (DESIGN.md, Seeds)."
    )


def table3(metrics: Metrics) -> str:
    rows = metrics.rows
    lines = [
        "| policy | source | min error (m) | max error (m) | mean error (m) | std error (m) "
        "| touchdown speed mean / max (m/s) | success | timeouts | off pad / aborts |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, label in ROWS.items():
        r = rows[key].summary
        e, v = r.landing_error_m, r.touchdown_speed_m_s
        # touchdowns > 2 m from the pad (unsafe) / flights ended in the air (pad not found);
        # "—" in metrics written before they were counted
        unsafe = "—" if r.off_pad is None else f"{r.off_pad} / {r.aborts}"
        lines.append(
            f"| {label} | **ours** | {fmt(e.min)} | {fmt(e.max)} | {fmt(e.mean)} | "
            f"{fmt(e.std)} | {fmt(v.mean)} / {fmt(v.max)} | {pct(r.success_rate)} | "
            f"{r.timeouts} | {unsafe} |"
        )
        paper = PAPER_TABLE3.get(key)
        if paper is None:
            lines.append(f"| {label} | paper | — | — | — | — | — | — | — | — |")
        else:
            td = (
                f"≈ {PAPER_VISION_TERMINAL_SPEED_M_S:g} (§5.5, qualitative)"
                if key == "vision"
                else "not reported"
            )
            lines.append(
                f"| {label} | paper | {paper['min']:.2f} | {paper['max']:.2f} | "
                f"{paper['mean']:.2f} | {paper['std']:.2f} | {td} | not reported | — | — |"
            )
    return "\n".join(lines)


def _ms(d: dict[str, Any], key: str) -> float | None:
    v = d.get(key)
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def runtime(metrics: Metrics, path: Path) -> str:
    timing = metrics.timing
    if not timing:
        return (
            f"`{path}` has no `timing` object (the eval stage writes it with "
            "`training.stages.eval.inference_timing`); no runtime comparison for this run."
        )
    pol = timing.get("policy") if isinstance(timing.get("policy"), dict) else {}
    mpc = timing.get("mpc") if isinstance(timing.get("mpc"), dict) else {}
    shipped = pol.get("shipped") if isinstance(pol.get("shipped"), dict) else {}
    style = pol.get("paper_style") if isinstance(pol.get("paper_style"), dict) else {}
    mpc_ms, pol_ms = _ms(mpc, "median_ms"), _ms(shipped, "median_ms")
    base_ms, style_ms = _ms(mpc, "baseline_median_ms"), _ms(style, "median_ms")
    p = PAPER_RUNTIME_S
    paper_ratio = p["mpc_mean"] / p["policy_mean"]

    def ratio(a: float | None, b: float | None) -> str:
        return f"{a / b:.2f}×" if a is not None and b else "n/a"

    def params(d: dict[str, Any]) -> str:
        n = d.get("parameters")
        return f", {n:,} parameters" if isinstance(n, int) else ""

    lines = [
        "| per control step | ours, median (tail) | paper (mean ± std) |",
        "|---|---:|---:|",
        f"| MPC expert (`expert.mpc`, OSQP warm-started) | {fmt(mpc_ms)} ms "
        f"(p95 {fmt(_ms(mpc, 'p95_ms'))}) | {1000 * p['mpc_mean']:.0f} ± "
        f"{1000 * p['mpc_std']:.0f} ms |",
        f"| paper-style MPC (CVXPY, rebuilt each call; `expert.bench`) | {fmt(base_ms, 1)} ms "
        f"(p95 {fmt(_ms(mpc, 'baseline_p95_ms'), 1)}) | — |",
        f"| CNN + LSTM policy, shipped size{params(shipped)} | {fmt(pol_ms)} ms "
        f"(p99 {fmt(_ms(shipped, 'p99_ms'))}) | {1000 * p['policy_mean']:.1f} ± "
        f"{1000 * p['policy_std']:.1f} ms |",
        f"| paper-style CNN-MLP + LSTM-MLP (our reconstruction{params(style)}) | "
        f"{fmt(style_ms)} ms (p99 {fmt(_ms(style, 'p99_ms'))}) | — |",
        f"| **ratio MPC / policy** | {ratio(mpc_ms, pol_ms)} | {paper_ratio:.1f}× |",
        f"| ratio paper-style MPC / paper-style network | {ratio(base_ms, style_ms)} | — |",
    ]
    text = "\n".join(lines)
    if mpc_ms is not None and pol_ms is not None:
        if mpc_ms < pol_ms:
            text += (
                f"\n\nOur MPC expert is *faster* per step than our policy ({fmt(mpc_ms)} ms vs "
                f"{fmt(pol_ms)} ms), so the paper's {paper_ratio:.1f}× speed-up of the policy "
                "over the expert does not reproduce here: it comes from how the paper's MPC is "
                "solved. Solved the paper's way (the CVXPY row) the MPC takes "
                f"{fmt(base_ms, 1)} ms, {ratio(base_ms, style_ms)} a paper-style network's time."
            )
        else:
            text += (
                f"\n\nOur policy is {ratio(mpc_ms, pol_ms)} faster per step than our MPC "
                f"(paper: {paper_ratio:.1f}×)."
            )
    text += (
        f"\n\nTimed in the run's eval stage on its machine (one thread, batch 1; "
        f"{pol.get('steps', '?')} policy steps, {mpc.get('samples', '?')} MPC solves, "
        f"{mpc.get('baseline_samples', '?')} CVXPY solves); the paper's figures are from its "
        "own hardware, so compare ratios, not milliseconds."
    )
    return text


def standing(metrics: Metrics) -> tuple[str, tuple[bool, ...]]:
    """The paper-world targets (:data:`~training.report.targets.TARGETS`): a summary line and
    the table; the met flags in target order."""
    table, met, missed = targets_standing(TARGETS, metrics.rows, label=ROWS.__getitem__)
    summary = f"**{sum(met)} of {len(TARGETS)} paper-world targets met.** " + (
        "Not met: " + "; ".join(missed) + "." if missed else "All targets are met."
    )
    return summary + "\n\n" + table, tuple(met)


def trajectory_caption(traces: dict[str, Trace], seed: int, episode: int) -> str:
    parts = []
    for row, tr in traces.items():
        state = "landed" if tr.landed else "timed out"
        if tr.eval_error_m is None:
            check = "no eval record for this episode"
        elif abs(tr.eval_error_m - tr.landing_error_m) <= 1e-6:
            check = "as in its eval episode"
        else:
            check = f"**eval recorded {fmt(tr.eval_error_m)} m — this flight differs**"
        parts.append(f"{ROWS[row]} {state}, error {fmt(tr.landing_error_m)} m ({check})")
    return f"Seed {seed}, episode {episode}: " + "; ".join(parts) + "."


def regenerate_eval(run: Path, metrics: Metrics) -> str:
    """The commands that rerun the eval stage of ``run`` (it skips a finished stage)."""
    profile = metrics.profile.name
    return f"rm {run}/stages/eval.json && visland train eval --run {run} --profile {profile}"


def rollouts_text(prof: dict[str, Any]) -> str:
    """How a run's DAgger learner rollouts flew (its profile's ``rollouts`` key)."""
    how = prof.get("rollouts")
    if how == Transport.MAVLINK:
        return (
            "flown by the learner through `visland sitl` + `visland companion` processes over "
            f"MAVLink/UDP in lockstep ({prof.get('workers', 1)} pairs side by side; the SITL's "
            "logs relabelled)"
        )
    if how == Transport.INPROCESS:
        return "flown in process (the gymnasium env)"
    return "flown in process (the run predates the profile's `rollouts` key)"


def header(command: str, metrics: Metrics, prov: Provenance, mismatches: list[str] | None) -> str:
    mpath = prov.run / "metrics.json"
    stage_commits = sorted(
        f"{name} `{short(rec.git_commit)}`"
        for name, rec in metrics.stages.items()
        if rec is not None and rec.git_commit
    )
    if mismatches:
        reflown = (
            f"- **Re-flying does not reproduce the eval records**: {'; '.join(mismatches)}. "
            "Lockstep flights are meant to be bit-for-bit deterministic (DESIGN.md), so code, "
            "checkpoint or environment differ from what the eval stage flew; regenerate it "
            f"(`{regenerate_eval(prov.run, metrics)}`) and this report.\n"
        )
    elif mismatches is not None:
        reflown = (
            "- Every trajectory flight below reproduces its eval record (landing error within "
            "1e-6 m).\n"
        )
    else:
        reflown = ""
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    return f"""# visland results — paper Table 3, runtime and figures

> Generated by `{command}` on {now}, code at `{prov.code_commit}`. Do not edit: every
> number and figure below is read from `{mpath}` (or computed from it, or flown from the run's
> checkpoints) by that command; the paper's numbers are constants in `training/paper.py`
> citing the paper's sections. Rerun the command to regenerate.

- Run: `{prov.run}`, profile `{metrics.profile.name}`, eval stage at commit
  `{prov.run_commit}`{"; stages: " + ", ".join(stage_commits) if stage_commits else ""}.
- {_seed_line(metrics)}
- DAgger learner rollouts: {rollouts_text(metrics.profile.to_dict())}.
{reflown}- Success = landing error ≤ 1 m, vertical touchdown speed ≤ 1 m/s, tilt ≤ 20°;
  touchdown speed in the table is the norm of the velocity at first contact (DESIGN.md,
  Metrics).
"""
