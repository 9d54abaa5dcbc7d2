"""``visland demo``: the shipped vision policy lands the simulated drone, over MAVLink.

The demo is the product as it would fly: ``visland fly`` (:mod:`training.exec.fly`) starts the
SITL and the companion as two processes talking MAVLink over UDP, the companion flies the shipped
CNN+LSTM policy (``models/visland_vision.pt``: camera, radar, IMU — no ground truth) through
``episodes`` landings in lockstep, and the SITL's own ground truth scores each touchdown. Then
the demo prints one row per landing (failures included, with the criterion that failed), the
summary and the companion's frame→setpoint latency, the MCAP flight logs of both processes,
and one PNG of all the flights (:func:`tools.log_plots.plot_flights`).

The default seed is the evaluation seed (1 000 000, the one the model card's 300 evaluation
episodes use, disjoint from every training seed): the demo flies the first episodes of that
set, whatever they show.

Both processes are always stopped by PID (``fly`` does it on success, failure and Ctrl-C).
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from companion.contract.topics import TOPIC_SCENARIO
from companion.files import sha256_file
from sitl_sim.metrics import (
    SUCCESS_MAX_ERROR_M,
    SUCCESS_MAX_TILT_DEG,
    SUCCESS_MAX_VERTICAL_SPEED_M_S,
)
from tools.log_plots import plot_flights
from tools.logtool import fmt_value
from training.exec.fly import FlyConfig, fly
from training.provenance import SHIPPED_MODEL
from training.seeds import EVAL_SEED

__all__ = ["EVAL_SEED", "SHIPPED_MODEL", "DemoConfig", "DemoError", "run", "write_report"]


MARKER = ".visland-demo"
"""File that marks a folder as a demo output folder, so a new demo may replace its contents."""
_OUTPUTS = ("sitl", "companion", "sitl.log", "companion.log", "companion.json")
_OUTPUTS_OWN = ("flights.png", "demo.json")


class DemoError(ValueError):
    """A user error before anything flies (bad policy file, scenario, output folder, count)."""


@dataclass(frozen=True)
class DemoConfig:
    """Options of ``visland demo``."""

    policy: str = str(SHIPPED_MODEL)
    """Checkpoint path (default: the shipped model), or ``expert`` / ``cascade``."""
    episodes: int = 3
    """Landings to fly: episodes ``0..episodes-1`` of ``seed``."""
    seed: int = EVAL_SEED
    """Scenario seed (default: the evaluation seed, see :data:`EVAL_SEED`)."""
    scenario: Path | None = None
    """Scenario TOML (default: configs/scenario.toml, the paper's initial states)."""
    out: Path = Path("runs/demo")
    """Output folder: logs, ``flights.png``, ``demo.json`` (a previous demo there is replaced)."""
    progress: bool = True
    """Print ``fly: k/N episodes`` on stderr while flying."""
    live: str = ""
    """``[HOST:]PORT`` of a live view in Foxglove ('' = off)."""


def _rel(path: str | Path, base: Path | None = None) -> str:
    """``path`` relative to ``base`` (default: the working directory) when it lies below it
    (shorter to read)."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to((base or Path.cwd()).resolve()))
    except ValueError:
        return str(path)


def _check_policy(policy: str) -> str:
    """The policy as the companion will be given it, and a one-line description.

    Raises:
        DemoError: the checkpoint is missing or unreadable (with what to do about it).
    """
    if policy in ("expert", "cascade"):
        return f"{policy} (privileged: flies on ground truth, a simulator-only baseline)"
    from companion.policy_net import CheckpointError, load_policy

    path = Path(policy).expanduser().resolve()
    try:
        net = load_policy(path)
    except CheckpointError as exc:
        hint = (
            "restore it with `git checkout -- models/visland_vision.pt`, or train and ship one: "
            "`visland pipeline --profile quick --out runs/quick && visland ship --run runs/quick`"
            if path == SHIPPED_MODEL.resolve()
            else "pass --policy with a checkpoint written by `visland train`/`pipeline`"
        )
        raise DemoError(f"policy {exc}; {hint}") from None
    kind = "vision: camera, radar, IMU, no ground truth" if not net.privileged else "privileged"
    return f"{_rel(path)} ({kind})"


def _prepare_out(out: Path) -> None:
    """Create ``out``, or clear a previous demo's outputs from it (never anything else).

    Raises:
        DemoError: ``out`` is a file, or a non-empty folder that no demo made.
    """
    if out.exists() and not out.is_dir():
        raise DemoError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not (out / MARKER).is_file():
            raise DemoError(
                f"--out {out}: folder not empty and not made by `visland demo` (no {MARKER}); "
                "pick another --out or empty it"
            )
        for name in (*_OUTPUTS, *_OUTPUTS_OWN):
            target = out / name
            if target.is_dir():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("made by `visland demo`; the next demo replaces this folder's logs\n")


def _why_not(row: dict[str, Any]) -> str:
    """``success`` or which success criterion failed (DESIGN.md: Episodes)."""
    if row["success"]:
        return "success"
    if not row["landed"]:
        return f"FAILED: timeout after {row['time_s']:.0f} s"
    why = []
    if not row["landing_error_m"] <= SUCCESS_MAX_ERROR_M:
        why.append(f"landing error {row['landing_error_m']:.2f} m > {SUCCESS_MAX_ERROR_M:g} m")
    vz = row["touchdown_vertical_speed_m_s"]
    if not vz <= SUCCESS_MAX_VERTICAL_SPEED_M_S:
        why.append(f"vertical speed {vz:.2f} m/s > {SUCCESS_MAX_VERTICAL_SPEED_M_S:g} m/s")
    if not row["tilt_deg"] <= SUCCESS_MAX_TILT_DEG:
        why.append(f"tilt {row['tilt_deg']:.1f} deg > {SUCCESS_MAX_TILT_DEG:g} deg")
    return "FAILED: " + ", ".join(why)


def _initial_states(rows: list[dict[str, Any]]) -> list[dict[str, Any] | None]:
    """Each episode's sampled initial state, from its SITL log's ``/episode/scenario``."""
    from companion.flightlog import read_log

    states = []
    for row in rows:
        msgs = read_log(row["log"], topics=[TOPIC_SCENARIO]).topic(TOPIC_SCENARIO)
        states.append(msgs[0].get("initial_state") if msgs else None)
    return states


def _companion_logs(out: Path, episodes: int) -> tuple[list[str | None], list[str]]:
    """The companion's log of each episode, and every companion log (for an honest list).

    The companion numbers its flights itself; the flights that flew the policy pair with the
    SITL's episodes in order. When their count differs (a restart, an aborted flight) no pairing
    is claimed and only the full list is given.
    """
    every = [str(p) for p in sorted((out / "companion").glob("*.mcap"))]
    try:
        flights = json.loads((out / "companion.json").read_text() or "{}").get("flights", [])
    except (OSError, ValueError):
        return [None] * episodes, every
    flown = [f.get("log_path") for f in flights if f.get("policy_commands", 0) > 0]
    if len(flown) != episodes:
        return [None] * episodes, every
    return flown, every


def _json_ready(value: Any) -> Any:
    """NaN/inf as null (JSON has none: null means "not defined", e.g. no touchdown)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    return value


def _write_header(
    episodes: int, seed: int, scenario: str, description: str, out: TextIO, base: Path | None
) -> None:
    """The demo's first lines: what flies, where, how (printed before anything flies)."""
    seed_note = " (the evaluation seed)" if seed == EVAL_SEED else ""
    out.write(
        f"visland demo — {episodes} landing(s), episodes 0..{episodes - 1} of seed "
        f"{seed}{seed_note}, scenario {_rel(scenario, base)}\npolicy {description}\n"
        "SITL (`visland sitl`) and companion (`visland companion`) run as two processes talking "
        "MAVLink 2 over UDP on 127.0.0.1, in lockstep\n"
    )


def write_report(report: dict[str, Any], out: TextIO, base: Path | None = None) -> None:
    """The demo's whole printout — header, one row per landing, summary, latency, log paths —
    from its report (:func:`run`'s return value, or ``demo.json`` read back); paths relative to
    ``base`` (default: the working directory) where they lie below it."""
    _write_header(
        report["episodes"],
        report["seed"],
        report["scenario"],
        report["policy_description"],
        out,
        base,
    )
    _write_results(report, out, base)


def _write_results(report: dict[str, Any], out: TextIO, base: Path | None) -> None:
    """Everything the demo prints after flying (see :func:`write_report`)."""
    w = out.write
    w(
        f"\n{'ep':>3} {'start N, E [m]':>15} {'alt [m]':>8} {'time [s]':>9} {'error [m]':>10} "
        f"{'v_down [m/s]':>13} {'tilt [deg]':>11}  result\n"
    )
    for row, start in zip(report["per_episode"], report["initial_states"], strict=True):
        if start:
            n, e, d = start["pos_ned_m"]
            where, alt = f"{n:+6.1f}, {e:+6.1f}", f"{-d:8.1f}"
        else:
            where, alt = f"{'?':>14}", f"{'?':>8}"
        w(
            f"{row['episode']:>3} {where:>15} {alt} {fmt_value(row['time_s'], '9.1f')} "
            f"{fmt_value(row['landing_error_m'], '10.3f')} "
            f"{fmt_value(row['touchdown_vertical_speed_m_s'], '13.2f')} "
            f"{fmt_value(row['tilt_deg'], '11.1f')}  {_why_not(row)}\n"
        )
    n = report["episodes"]
    ok = sum(1 for r in report["per_episode"] if r["success"])
    err = report["landing_error_m"]
    w(
        f"\n{ok} of {n} landings successful ({100 * report['success_rate']:.0f} %); landing error "
        f"mean {fmt_value(err['mean'])} m, max {fmt_value(err['max'])} m; timeouts "
        f"{report['timeouts']}.\n"
        f"Success = landing error <= {SUCCESS_MAX_ERROR_M:g} m, vertical speed <= "
        f"{SUCCESS_MAX_VERTICAL_SPEED_M_S:g} m/s, tilt <= {SUCCESS_MAX_TILT_DEG:g} deg at "
        "touchdown (SITL ground truth). Large-sample figures: models/MODEL_CARD.md.\n"
    )
    lat = report["latency_ms"]
    if lat.get("commands"):
        w(
            f"companion frame receipt -> setpoint sent: median {lat['median_ms']:.2f} ms, "
            f"p99 {lat['p99_ms']:.2f} ms over {lat['commands']} commands\n"
        )
    w(f"flown in {report['wall_s']:.1f} s wall (lockstep: as fast as this machine allows)\n")
    w("\nflight logs (MCAP: `visland log info FILE`, `visland log plot FILE`, or Foxglove):\n")
    for row, comp in zip(report["per_episode"], report["companion_logs"], strict=True):
        w(f"  episode {row['episode']}  SITL       {_rel(row['log'], base)}\n")
        if comp:
            w(f"             companion  {_rel(comp, base)}\n")
    if not any(report["companion_logs"]) and report["companion_logs_all"]:
        w("  companion logs (not paired with episodes):\n")
        for path in report["companion_logs_all"]:
            w(f"    {_rel(path, base)}\n")
    logs = [_rel(report[k], base) for k in ("sitl_stderr", "companion_stderr")]
    w(f"process output: {logs[0]}, {logs[1]}\n")
    w(f"plot of the flights: {_rel(report['plot'], base)}\n")


def run(cfg: DemoConfig, out: TextIO) -> dict[str, Any]:
    """Fly the demo, print it to ``out`` and return its report (``fly``'s, plus log paths).

    Keys added to :func:`training.exec.fly.fly`'s report: ``initial_states`` (per episode),
    ``companion_logs`` (per episode, None where unpaired), ``companion_logs_all``, ``plot``,
    ``sitl_stderr``, ``companion_stderr``, ``policy_description``. Also written to
    ``<out>/demo.json``.

    Raises:
        DemoError: bad input, before anything flies.
        training.exec.fly.FlyError: a process failed (both processes are stopped first).
    """
    if cfg.episodes < 1:
        raise DemoError(f"--episodes must be >= 1, got {cfg.episodes}")
    scenario = None
    if cfg.scenario is not None:
        from sitl_sim.scenario import load_scenario

        scenario = Path(cfg.scenario).expanduser().resolve()
        load_scenario(scenario)  # a bad file stops here, naming the field (SimError)
    description = _check_policy(cfg.policy)
    policy = cfg.policy if cfg.policy in ("expert", "cascade") else str(Path(cfg.policy).resolve())
    out_dir = Path(cfg.out).expanduser().resolve()  # fly's processes run in the repository
    _prepare_out(out_dir)

    scenario_text = str(scenario) if scenario else "configs/scenario.toml"
    _write_header(cfg.episodes, cfg.seed, scenario_text, description, out, None)
    out.flush()
    report = fly(
        FlyConfig(
            policy=policy,
            episodes=cfg.episodes,
            seed=cfg.seed,
            scenario=str(scenario) if scenario else None,
            out=str(out_dir),
            progress=cfg.progress,
            live=cfg.live,
            scene=True,  # the logs open in Foxglove with the layout as the flight looked live
        )
    ).to_dict()  # the demo's report is fly's JSON object, its own keys added (demo.json)
    rows = report["per_episode"]
    report["policy_description"] = description
    report["policy_sha256"] = None if policy in ("expert", "cascade") else sha256_file(policy)
    report["initial_states"] = _initial_states(rows)
    report["companion_logs"], report["companion_logs_all"] = _companion_logs(out_dir, cfg.episodes)
    report["sitl_stderr"] = str(out_dir / "sitl.log")
    report["companion_stderr"] = str(out_dir / "companion.log")
    ok = sum(1 for r in rows if r["success"])
    plot = plot_flights(
        [r["log"] for r in rows],
        out_dir / "flights.png",
        title=f"visland demo: {Path(cfg.policy).name}, seed {cfg.seed} — "
        f"{ok} of {len(rows)} landings successful",
        labels=[f"episode {r['episode']}" for r in rows],
    )
    report["plot"] = str(plot.out)
    _write_results(report, out, None)
    tmp = out_dir / "demo.json.tmp"
    tmp.write_text(json.dumps(_json_ready(report), indent=2, default=str) + "\n")
    os.replace(tmp, out_dir / "demo.json")
    return report
