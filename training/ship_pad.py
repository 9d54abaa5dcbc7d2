"""The card of a run that taught a pad (``training.pad_teach``), which :func:`training.ship.ship`
installs as ``models/visland_vision_<pad>.pt`` beside ``models/visland_vision_<pad>.md``: every
number read from the run's ``pad_metrics.json``, suite reports, stage records and
``pipeline_time.json``.

The card's targets are issue 33's for a taught pad: on each condition of the pad's suite, at
least :data:`TARGET_SUCCESS` of the landings and a mean landing error of at most
:data:`TARGET_MEAN_ERROR_M`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from companion.files import sha256_file
from companion.policy_net import ESTIMATOR_FIELDS, NetConfig, load_networks
from training.pad_teach import PAD_VALIDATION_SUCCESS, PadMetrics, SourceRecord, file_text
from training.reports import EvalReport, SuiteReport

__all__ = [
    "TARGET_MEAN_ERROR_M",
    "TARGET_SUCCESS",
    "estimator_text",
    "is_pad_run",
    "load_pad_metrics",
    "pad_card",
    "stage_times",
]

TARGET_SUCCESS = 0.98
TARGET_MEAN_ERROR_M = 0.15


def is_pad_run(run: str | Path) -> bool:
    """Whether ``run`` is a run folder that teaches a pad (its ``profile.json`` names one)."""
    path = Path(run) / "profile.json"
    try:
        return bool(json.loads(path.read_text()).get("pad"))
    except (OSError, ValueError, AttributeError):
        return False


def load_pad_metrics(run: Path) -> PadMetrics:
    """``run``'s ``pad_metrics.json`` (its eval stage's record).

    Raises:
        FileNotFoundError: the run's eval stage has not finished.
    """
    path = run / "pad_metrics.json"
    if not path.exists():
        raise FileNotFoundError(f"{path}: run the pad run's eval stage first")
    return PadMetrics.from_dict(json.loads(path.read_text()), str(path))


def _num(value: float | None, digits: int = 3, unit: str = " m") -> str:
    if value is None or not math.isfinite(value):
        return "n/a"
    return f"{value:.{digits}f}{unit}"


def _cells(r: EvalReport) -> list[str]:
    s = r.summary
    return [
        f"{100 * (s.success_rate or 0.0):.1f} % ({r.episodes})",
        _num(s.landing_error_m.mean),
        _num(s.landing_error_m.max),
        _num(s.touchdown_speed_m_s.mean, unit=" m/s"),
    ]


def suite_table(report: SuiteReport, baseline: SuiteReport, names: tuple[str, str]) -> str:
    """Markdown: per condition, success (episodes), mean and max landing error, mean touchdown
    speed of the taught model and of the model it started from."""
    cols = ("success", "mean", "max", "touchdown")
    head = " | ".join(f"{n}: {c}" for n in names for c in cols)
    lines = [f"| condition | {head} |", "|---|" + "---:|" * (2 * len(cols))]
    for name, r in report.conditions.items():
        b = baseline.conditions.get(name)
        theirs = _cells(b) if b is not None else ["—"] * len(cols)
        lines.append(f"| {name} | {' | '.join(_cells(r) + theirs)} |")
    return "\n".join(lines)


def targets(report: SuiteReport) -> tuple[str, int, int]:
    """Markdown table of the targets per condition; (table, met, total)."""
    rows, met = [], 0
    for name, r in report.conditions.items():
        s = r.summary
        success = s.success_rate or 0.0
        mean = s.landing_error_m.mean
        for what, value, ok in (
            (f"success ≥ {100 * TARGET_SUCCESS:.0f} %", f"{100 * success:.1f} %", success),
            (f"error mean ≤ {TARGET_MEAN_ERROR_M} m", _num(mean), mean),
        ):
            good = (
                ok >= TARGET_SUCCESS
                if what.startswith("success")
                else ok is not None and math.isfinite(ok) and ok <= TARGET_MEAN_ERROR_M
            )
            met += bool(good)
            rows.append(f"| {name}: {what} | {value} | {'yes' if good else '**no**'} |")
    table = "\n".join(["| target | value | met |", "|---|---:|:---:|", *rows])
    return table, met, len(rows)


def stage_times(run: Path) -> tuple[str, float, int]:
    """The sessions of ``pipeline_time.json`` as text (per stage), their total seconds and
    their number."""
    path = run / "pipeline_time.json"
    sessions: list[dict[str, Any]] = (
        json.loads(path.read_text()).get("sessions", []) if path.exists() else []
    )
    total = sum(s["seconds"] for s in sessions)
    parts = []
    for k, s in enumerate(sessions, 1):
        per = s.get("stage_seconds") or {}
        detail = ", ".join(f"{n} {v / 60:.1f} min" for n, v in per.items()) or "nothing to run"
        parts.append(f"session {k}: {s['seconds'] / 60:.1f} min ({detail})")
    return "; ".join(parts) or "not recorded", total, len(sessions)


def estimator_text(source: SourceRecord, cfg: NetConfig) -> str:
    """Whose controller and estimator the taught model flies: the ``--from`` model's, with the
    estimator settings of the run's profile that differ from it named (``min_fix_altitude_m``,
    scaled with the pad, is the card's own line). A ``--from`` file that is gone or changed
    since the run cannot be compared, and the card says so rather than guess."""
    path = Path(source.checkpoint)
    model = f"`{path.name}` (sha256 `{source.sha256[:16]}…`)"
    if not path.is_file() or sha256_file(path) != source.sha256:
        return f"the controller of {model} with the estimator settings of the run's profile"
    before = load_networks(path)[0]
    changed = [
        f"`{k}` {getattr(cfg, k)} (`{path.name}`: {getattr(before, k)})"
        for k in ESTIMATOR_FIELDS
        if k != "min_fix_altitude_m" and getattr(cfg, k) != getattr(before, k)
    ]
    if not changed:
        return f"the controller and estimator of {model}"
    return f"the controller and estimator of {model}, its estimator with {', '.join(changed)},"


def pad_card(run: Path, m: PadMetrics, shipped: Any, variant: str | None) -> str:
    """The card of ``run``'s model as ``shipped`` (a :class:`training.ship.InstalledModel`)."""
    policy, dst, extra_sections = shipped.policy, shipped.path, shipped.extra_sections
    report, baseline = SuiteReport.load(m.report), SuiteReport.load(m.baseline)
    source = Path(m.source.checkpoint)
    table = suite_table(report, baseline, (dst.name, source.name))
    target_table, met, total = targets(report)
    times, total_s, _ = stage_times(run)
    n_params = shipped.n_params
    pr, vr = m.perception, m.vision
    lo, hi = m.pad.start_altitude_m
    prior = next((v for v in vr.validation if v.checkpoint == vr.selected), None)
    first = vr.validation[0] if vr.validation else None  # the controller as it came
    if vr.fits:
        rounds = (
            f"the controller as it came landed {_num(100 * (first.success_rate or 0.0), 1, ' %')}"
            f" (< {100 * PAD_VALIDATION_SUCCESS:.0f} %): {len(vr.fits)} vision DAgger round(s)"
            " flew, and validation picked among them"
            if first
            else f"{len(vr.fits)} vision DAgger round(s) flew"
        )
    elif first and (first.success_rate or 0.0) >= PAD_VALIDATION_SUCCESS:
        rounds = "no vision DAgger round was needed: the controller flies the taught CNN as it is"
    else:
        rounds = f"profile `{m.profile.name}` flies no vision DAgger round"
    timing = m.timing.get("policy", {}).get("shipped", {})
    pad_file = file_text(Path(m.pad.file))
    from_text = f"--from {m.source.run}" if m.source.run else f"--from {m.source.checkpoint}"
    worlds = m.profile.worlds or "configs/scenario.toml"
    title = f"pad `{m.pad.name}`" + (f" in the worlds of `{worlds}`" if variant else "")
    return f"""# visland vision landing policy `{dst.name}` for {title} — model card

`{dst.name}` (sha256 `{sha256_file(dst)[:16]}…`, {dst.stat().st_size // 1024} KiB, {n_params}
parameters): {estimator_text(m.source, policy.config)} with its CNN retrained to see the pad
`{m.pad.name}` (`{pad_file}`, {m.pad.size_m[0]:g} × {m.pad.size_m[1]:g} m). Same inputs and
outputs as `{source.name}`; fly it only over this pad, started (or flown in) between
{lo:g} and {hi:g} m — the pad's envelope (`visland pad info --pad {m.pad.name}`).

## How it was made

    visland pipeline --profile {m.profile.name} --pad {pad_file} {from_text} --out {run}
    visland ship --run {run}{f" --name {variant}" if variant else ""}

- commit: `{m.git_commit}`; started at `{m.source.commit}`.
- worlds: the profile's (`{worlds}`) with `[pad] design`
  set and every start altitude × {m.pad.altitude_scale:g} (`{run}/worlds/`).
- perception: {pr.pose_images} frames rendered at sampled poses with the pad (altitudes
  × {m.pad.altitude_scale:g}), {pr.epochs} epoch(s) from `{source.name}`'s CNN
  ({pr.train_images} training frames); held-out frames: bearing error median
  {_num(pr.pose_val_bearing_error_px_median, 2, " px")}, p95
  {_num(pr.pose_val_bearing_error_px_p95, 2, " px")}, visibility accuracy
  {_num(pr.pose_val_visibility_accuracy, 3, "")}.
- vision: validation ({m.profile.validation_episodes} episodes, seed
  {m.profile.validation_seed}, disjoint from evaluation) — the selected candidate landed
  {_num(100 * (prior.success_rate or 0.0) if prior else None, 1, " %")}, mean error
  {_num(prior.mean_error_m if prior else None)}; {rounds}. The estimator takes horizontal
  fixes down to {policy.config.min_fix_altitude_m:g} m (`{source.name}`: 1.5 m; scaled with the
  pad: below it the camera sees a piece of the pad).
- wall time (`pipeline_time.json`, 2 CPU cores): {total_s / 60:.1f} min — {times}.

## Results on the pad's suite (`{m.suite}`, seed {m.eval_seed})

{table}

Each cell: success (episodes), mean and max landing error, mean touchdown speed. Beside it,
`{source.name}` before the pad was taught, on the same episodes. Success = landing error
≤ 1 m, vertical touchdown speed ≤ 1 m/s, tilt ≤ 20°.

### Targets: {met} of {total} met

{target_table}

{extra_sections}## Runtime (one thread, batch 1)

This policy: median {_num(timing.get("median_ms"), 3, " ms")} per step, p99
{_num(timing.get("p99_ms"), 3, " ms")}.

## Limits

Trained and evaluated only in visland's simulator, on the pad as its file draws it (printed at
true size, matte), over procedural grounds, Earth and Mars. A real camera, real light and a
real pad need a check before flight: `visland pad check` on a photo of the laid-out pad, then
the companion's shadow mode (`docs/deploy.md`).
"""
