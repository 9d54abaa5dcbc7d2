"""Ship a run's vision policy into ``models/`` with a MODEL_CARD.md written from its metrics.

Every number in the card is read from the run's ``metrics.json`` and stage records — nothing is
typed by hand — and the card names the command, commit, data and time that produced it.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.files import sha256_file
from companion.policy_net import load_policy
from training.paper import PAPER_RUNTIME_S
from training.provenance import MODEL_NAME, SHIPPED_MODEL
from training.report.markdown import rollouts_text, table3
from training.report.metrics import load_metrics
from training.report.targets import fmt, value_text
from training.reports import SuiteReport
from training.ship_pad import is_pad_run, load_pad_metrics, pad_card, stage_times

__all__ = ["card_file", "extra_suite_section", "ship", "variant_file"]


def variant_file(variant: str | None) -> str:
    """The shipped model's file name: ``visland_vision.pt`` (the default model, its card
    ``MODEL_CARD.md``) or, for a variant (``visland ship --name sites``),
    ``visland_vision_<variant>.pt`` with its own card beside it. A name that is not a plain
    file-name word is refused."""
    if variant is None:
        return SHIPPED_MODEL.name
    if not MODEL_NAME.match(variant):
        raise ValueError(
            f"--name {variant!r}: expected letters, digits, '_', '-' or '.' (it names "
            "models/visland_vision_<name>.pt)"
        )
    return f"{SHIPPED_MODEL.stem}_{variant}{SHIPPED_MODEL.suffix}"


def card_file(model: Path) -> Path:
    """The card beside a shipped ``model``: ``MODEL_CARD.md`` for the default model,
    ``<model stem>.md`` for any other (a variant, a taught pad)."""
    return (
        model.parent / "MODEL_CARD.md"
        if model.name == SHIPPED_MODEL.name
        else model.with_suffix(".md")
    )


def extra_suite_section(path: Path, model: Path) -> str:
    """A suite report flown with this run's model outside its eval stage (``visland eval
    --suite FILE --policy ... --json``), as a card section. A report of another model (its
    policy file's sha256 differs from the shipped file's) is refused."""
    report = SuiteReport.load(path)
    sha, expected = report.policy_sha256, sha256_file(model)
    if sha is None and Path(report.policy).is_file():
        sha = sha256_file(report.policy)
    if sha != expected:
        raise ValueError(
            f"{path}: policy {report.policy} (sha256 {str(sha)[:16]}…) is not the model "
            f"being shipped, {model} (sha256 {expected[:16]}…); fly the suite with that file"
        )
    rows = [
        "| condition | success | mean | max | touchdown | off pad | aborts |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in report.conditions.items():
        s = r.summary
        rows.append(
            f"| {name} | {100 * s.success_rate:.1f} % ({r.episodes}) "
            f"| {value_text(s.landing_error_m.mean, 'm')} "
            f"| {value_text(s.landing_error_m.max, 'm')} "
            f"| {value_text(s.touchdown_speed_m_s.mean, 'm/s')} "
            f"| {'—' if s.off_pad is None else s.off_pad} "
            f"| {'—' if s.aborts is None else s.aborts} |"
        )
    table = "\n".join(rows)
    return f"""## Results on `{report.suite}` (seed {report.seed})

    visland eval --suite {report.suite} --policy {report.policy} --json > {path}

{table}

Off pad: touchdowns more than 2 m from the pad (the unsafe failures); aborts: flights ended
in the air for want of a pad. On a site the error and touchdown speed are in the pad's frame.

"""


@dataclass(frozen=True)
class InstalledModel:
    """What :func:`install_model` put in place, for the card written beside it."""

    policy: Any
    path: Path
    extra_sections: str
    n_params: int


def install_model(
    run: Path, out: Path, name: str, suite_reports: Sequence[str | Path]
) -> InstalledModel:
    """Copy ``run``'s vision checkpoint to ``out/name`` with its ONNX export. The checkpoint
    is loaded first (a corrupt or foreign file is refused) and each suite report is checked
    against it (a report of another model is refused) before anything in ``out`` is replaced;
    returns the loaded policy, the installed path and the reports' card sections."""
    src = run / "checkpoints" / "vision.pt"
    policy = load_policy(src)
    extra_sections = "".join(extra_suite_section(Path(p), src) for p in suite_reports)
    out.mkdir(parents=True, exist_ok=True)
    dst = out / name
    shutil.copyfile(src, dst)
    from companion.onnx_export import export_onnx

    export_onnx(dst)
    n_params = sum(p.numel() for p in policy.control.parameters()) + sum(
        p.numel() for p in policy.perception.parameters()
    )
    return InstalledModel(policy, dst, extra_sections, n_params)


def _suite_section(metrics: dict[str, Any], shipped: str) -> str:
    """The suite table beside the baseline's and issue 16's targets, when the eval stage flew
    the profile's suite (empty otherwise)."""
    if not metrics.get("suite"):
        return ""
    from training.report.suite import suite_comparison, suite_standing

    report = SuiteReport.load(metrics["suite"])
    baseline = None
    if metrics.get("suite_baseline"):
        baseline = SuiteReport.load(metrics["suite_baseline"])
    base_name = Path(baseline.policy).name if baseline else ""
    standing, met, total = suite_standing(report)
    base_line = (
        f"The baseline is {_baseline_words(base_name)} (`{base_name}`), flown on the same episodes."
        if baseline
        else ""
    )
    verdict = "All targets are met." if met == total else "Targets not met are marked **no**."
    which = _which_model(report, baseline, shipped, base_name) if baseline else ""
    suite_name = metrics["profile"].get("eval_suite") or report.suite
    return f"""## Results on the benchmark suite (`{suite_name}`, seed {report.seed})

{suite_comparison(report, baseline, (shipped, base_name))}

Each cell: success (episodes), mean and max landing error, mean touchdown speed.
{base_line}

### Issue 16's targets: {met} of {total} met

{verdict}

{standing}

{which}"""


def _baseline_words(base_name: str) -> str:
    """What a suite baseline is, by its file: the paper-world model (the robust profile's
    baseline) or the default shipped model (a variant's)."""
    return (
        "the default shipped model" if base_name == SHIPPED_MODEL.name else "the paper-world model"
    )


def _which_model(report: SuiteReport, baseline: SuiteReport, shipped: str, base_name: str) -> str:
    """Which model to fly where, from the two suite reports: the conditions where the baseline
    lands more often, or as often and at least 10 % closer on average. A variant measured
    against the default model is not the default: the default stays, the variant is for the
    sites its own tables show it better on."""
    better = []
    for name, report_r in report.conditions.items():
        base_r = baseline.conditions.get(name)
        if base_r is None:
            continue
        r, b = report_r.summary, base_r.summary
        ours_e, base_e = r.landing_error_m.mean, b.landing_error_m.mean
        if b.success_rate > r.success_rate or (
            b.success_rate == r.success_rate
            and ours_e is not None
            and base_e is not None
            and base_e < 0.9 * ours_e
        ):
            better.append(
                f"{name} ({100 * b.success_rate:.1f} % vs {100 * r.success_rate:.1f} %, "
                f"mean {base_e if base_e is None else round(base_e, 3)} m vs "
                f"{ours_e if ours_e is None else round(ours_e, 3)} m)"
            )
    if base_name == SHIPPED_MODEL.name:
        where = "; ".join(better) if better else "no condition of this suite"
        return (
            f"### Which model\n\n`{base_name}` stays the default. `{shipped}` is a variant "
            "for the conditions its own tables below show it better on; on this suite the "
            f"default model is better in: {where}.\n\n"
        )
    if not better:
        return (
            f"### Which model\n\n`{shipped}` everywhere: the paper-world model `{base_name}` is "
            "not better in any condition of the suite.\n\n"
        )
    return (
        f"### Which model\n\n`{shipped}` is the default. The paper-world model `{base_name}` "
        f"is better in: {'; '.join(better)} — fly it only in that world (still air, the paper's "
        "ground and vehicle).\n\n"
    )


def _limits(robust: bool) -> str:
    if robust:
        return (
            "Trained and evaluated only in visland's simulator: one pad design (4 m square with a\n"
            "cross, sized and tinted per episode), procedural grounds, a pinhole camera with\n"
            "simulated effects, the Table 1 vehicle scaled ±35 %, Earth and Mars. A real camera,\n"
            "real light and a real pad need new perception data before flight; start on hardware\n"
            "in the companion's shadow mode (`docs/deploy.md`)."
        )
    return (
        "Trained and evaluated only in visland's simulator: one pad design (4 m green square, red\n"
        "cross), one procedurally textured ground, the Table 1 vehicle, Earth gravity. A real\n"
        "camera, real lighting and a real pad need new perception data before flight; start on\n"
        "hardware in the companion's shadow mode (`docs/deploy.md`)."
    )


def _run_scenario(run: Path) -> str:
    """The scenario file the run flew (its ``profile.json``); the paper's by default."""
    path = run / "profile.json"
    scenario = json.loads(path.read_text()).get("scenario") if path.exists() else None
    return scenario or "configs/scenario.toml (paper 4.1)"


def ship(
    run: str | Path,
    out: str | Path = "models",
    variant: str | None = None,
    suite_reports: tuple[str | Path, ...] = (),
) -> Path:
    """Copy ``<run>/checkpoints/vision.pt`` to ``<out>/visland_vision.pt`` (a ``variant``:
    ``visland_vision_<variant>.pt``, :func:`variant_file`), export its ONNX graphs beside it
    (the board runtime; a previous model's export there would otherwise be refused as stale)
    and write its card: ``MODEL_CARD.md`` for the default model, ``<model stem>.md`` for a
    variant, so a variant never replaces the default model or its card. A run that taught a
    pad (:func:`training.ship_pad.is_pad_run`) ships as ``visland_vision_<pad>.pt`` (a variant
    still takes the variant's name: a run that taught the paper's pad in other worlds must not
    take the paper-world model's) with its pad card (:func:`training.ship_pad.pad_card`)
    beside it. ``suite_reports``: suites flown with the run's model outside its eval stage,
    each a section of the card. Returns the model file.

    Raises:
        FileNotFoundError: the run's eval stage has not finished.
        ValueError: a bad variant name, or a suite report of another model (before anything
            in ``out`` is replaced).
    """
    run, out = Path(run), Path(out)
    if is_pad_run(run):
        pad = load_pad_metrics(run)
        name = variant_file(variant) if variant else f"visland_vision_{pad.pad.name}.pt"
        shipped = install_model(run, out, name, suite_reports)
        card_file(shipped.path).write_text(pad_card(run, pad, shipped, variant))
        return shipped.path
    name = variant_file(variant)
    metrics_path = run / "metrics.json"
    if not metrics_path.exists():
        raise FileNotFoundError(f"{metrics_path}: run the pipeline's eval stage first")
    metrics = json.loads(metrics_path.read_text())
    shipped = install_model(run, out, name, suite_reports)
    policy, dst, extra_sections = shipped.policy, shipped.path, shipped.extra_sections
    prof = metrics["profile"]
    stages = metrics.get("stages", {})
    timing = metrics.get("timing", {})
    pol_t, mpc_t = timing.get("policy", {}), timing.get("mpc", {})
    _, total_s, sessions = stage_times(run)
    perception = stages.get("perception") or {}
    n_params = shipped.n_params
    paper_mpc_ms = 1000 * PAPER_RUNTIME_S["mpc_mean"]
    paper_pol_ms = 1000 * PAPER_RUNTIME_S["policy_mean"]
    cfg = policy.config
    inputs = (
        "128×128 mono8 downward camera (45° FOV), ATTITUDE, body rates, HIGHRES_IMU specific "
        "force, radar range"
    )
    if cfg.hover_input:
        inputs += (
            ", and the autopilot's hover thrust (PX4 `MPC_THR_HOVER` / ArduPilot "
            "`MOT_THST_HOVER`, read at connect time) — one model for heavier and lighter "
            "airframes and for Mars"
        )
    extras = [
        text
        for on, text in (
            (
                cfg.accel_bias_states,
                "acceleration-bias states (IMU bias, another planet's gravity)",
            ),
            (cfg.latency_compensation, "camera fixes at the image's exposure time"),
            (cfg.radar_gate_sigma > 0, f"a {cfg.radar_gate_sigma:g}-sigma radar gate"),
            (
                cfg.radar_terrain_slope_deg > 0,
                f"the radar read for ground up to {cfg.radar_terrain_slope_deg:g}° steep where "
                "its beam meets it",
            ),
            (
                cfg.acquire_threshold is not None,
                f"a bearing is a fix at pad probability ≥ {cfg.visibility_threshold:g}, the "
                f"first one at ≥ {cfg.acquire_threshold}",
            ),
            (
                cfg.unsure_threshold is not None,
                f"a bearing at ≥ {cfg.unsure_threshold} (unsure) is a fix only where it agrees "
                f"with the estimate, its noise {cfg.unsure_sigma_scale:g}× larger"
                + (
                    f", from a view tilted ≤ {cfg.unsure_max_tilt_deg:g}°"
                    if cfg.unsure_max_tilt_deg is not None
                    else ""
                ),
            ),
        )
        if on
    ]
    estimator = "Kalman pad estimator" + (f" ({'; '.join(extras)})" if extras else "")
    worlds = prof.get("worlds")
    data_where = (
        f"across the training worlds of `{worlds}` (each stage's flights split by share)"
        if worlds
        else f"the initial states of `{_run_scenario(run)}`"
    )
    suite_section = _suite_section(metrics, dst.name)
    suite_section += extra_sections
    ship_cmd = f"visland ship --run {run}" + (f" --name {variant}" if variant else "")
    ship_cmd += "".join(f" --suite-report {p}" for p in suite_reports)
    title = "" if variant is None else f" `{dst.name}`"
    card = f"""# visland vision landing policy{title} — model card

`{dst.name}` (sha256 `{sha256_file(dst)[:16]}…`, {dst.stat().st_size // 1024} KiB, {n_params}
parameters): CNN pad-bearing regressor + {estimator} + LSTM controller
(`companion/policy_net/`). Inputs: {inputs}. Output: `Command` (thrust_norm ∈ [0, 1], FRD body
rates), one per 10 Hz camera frame. It needs no ground truth: it can fly on hardware.

## How it was made

    visland pipeline --profile {prof["name"]} --out {run}
    {ship_cmd}

- commit: `{metrics.get("git_commit", "unknown")}`
- data: {prof["collect_episodes"]} expert (MPC) flights, seed {prof["collect_seed"]}
  (`{run}/flights/expert`),
  {data_where}; {prof["dagger_rounds"]} privileged DAgger
  rounds × {prof["dagger_rollouts"]} learner rollouts (seeds {prof["dagger_seed"]}+k);
  {prof["vision_rounds"]} vision DAgger rounds × {prof["vision_rollouts"]} rollouts (seeds
  {prof["vision_seed"]}+k), {rollouts_text(prof)}; every learner flight relabelled offline
  from its MCAP log.
- replay buffer: {prof["buffer_capacity"]} episodes FIFO, {prof["segment_steps"]}-step segments
  × {prof["batch_segments"]} per batch (paper 4.2).
- perception: {perception.get("train_images", "?")} training / {perception.get("val_images", "?")}
  validation frames (episode split 90/10); validation bearing error median
  {fmt(perception.get("val_bearing_error_px_median"), 2)} px, p95
  {fmt(perception.get("val_bearing_error_px_p95"), 2)} px.
- pipeline wall time recorded in `pipeline_time.json` (2 CPU cores): {total_s / 60:.1f} min
  over {sessions} completed session(s); an interrupted session is not recorded, and
  every stage run again counts (a finished run that takes new estimator settings flies vision
  and eval again), so this is more than one end-to-end run.
- determinism: on one machine, the same commit, profile and seeds train the same weights, stage
  by stage (`tests/test_pipeline_e2e.py` runs a tiny profile twice and compares every tensor);
  another machine's BLAS and thread count may round differently, and flights over MAVLink in
  real time are not lockstep-exact.

{suite_section}## Results in the paper's world ({metrics["episodes"]} evaluation episodes,
seed {metrics["eval_seed"]}, disjoint from training)

{table3(load_metrics(run))}

Success = landing error ≤ 1 m, vertical touchdown speed ≤ 1 m/s, tilt ≤ 20°. The paper's
rows are its Table 3 (§5.4): landing error only.

## Runtime (one thread, batch 1, same run)

- this policy: median {fmt(pol_t.get("shipped", {}).get("median_ms"))} ms per step, p99
  {fmt(pol_t.get("shipped", {}).get("p99_ms"))} ms;
- a paper-style CNN-MLP + LSTM-MLP (our reconstruction, the paper gives no sizes): median
  {fmt(pol_t.get("paper_style", {}).get("median_ms"))} ms;
- our MPC expert: median {fmt(mpc_t.get("median_ms"))} ms per solve
  (`visland bench mpc`); paper: MPC {paper_mpc_ms:.0f} ms, policy {paper_pol_ms:.1f} ms.

## Limits

{_limits(bool(worlds))}
"""
    card_file(dst).write_text(card)
    return dst
