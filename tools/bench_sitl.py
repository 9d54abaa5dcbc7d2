"""``visland bench sitl``: how fast a SITL + companion pair flies in lockstep, and where the
wall time of both processes goes.

In one run:

1. **the pair**: ``visland fly`` (:func:`training.exec.fly.fly`): the SITL
   (``python -m sitl_sim.mavlink``) and the real companion process flying the shipped model (or
   ``expert``, or any checkpoint) over UDP in lockstep, camera rendered for a vision policy.
   Each process times the parts of its own loop while a flight is in the air
   (:class:`~companion.contract.perf.LoopPerf`: the SITL logs its report at exit, the companion
   puts it in its JSON report); read back here;
2. **the floor**: the same simulator in process (:class:`~sitl_sim.simulator.Simulator`:
   physics, sensors, camera at 10 Hz), flown by the privileged CascadeLander for as many control
   periods as the pair flew, on episode 0's initial state.

Reported: ``realtime_factor`` = flight sim seconds per wall second of the SITL's flight window
(take-over to episode end; the HOLD hand-shake before it runs at wall-clock speed by design and
is left out), the same end to end (``fly``'s wall time: process start, hand-shakes), and
``realtime_factor_cpu`` = sim seconds per CPU second of both processes in their windows (what
the pair would reach with nothing overlapping on an idle machine; unlike wall time it hardly
moves when other work shares the machine: the figure to compare before/after a change). Per
process: the share of the window's wall time in ``physics``, ``render``, ``policy``,
``encode_decode`` (MAVLink, camera packets and flight-log writing; also split as ``mavlink``,
``camera``, ``log``), ``wait`` (blocked on the other process) and ``other``, and milliseconds
per frame of each. ``vs_in_process`` = the pair's real-time factor over the floor's. With
``repeats`` the pair flies that many times: the figures are the median run's, ``runs`` holds
each run's headline figures and their best and median.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from companion.contract.perf import parse_perf_line
from training.provenance import SHIPPED_MODEL

__all__ = ["SitlBenchConfig", "bench_sitl", "format_sitl_bench"]

_ENCODE_DECODE = ("mavlink", "camera", "log")


@dataclass(frozen=True)
class SitlBenchConfig:
    policy: str = str(SHIPPED_MODEL)
    """What the companion flies: a checkpoint, ``expert`` (the MPC) or ``cascade``."""
    runtime: str = "auto"
    """The companion's policy backend for a checkpoint: ``auto`` (as ``visland fly`` and the
    demo: ONNX Runtime where the export is beside the checkpoint), ``torch`` or ``onnx``."""
    episodes: int = 2
    """Flights of the pair (consecutive episodes of ``seed``)."""
    seed: int = 0
    scenario: str | None = None
    """Scenario TOML (default configs/scenario.toml)."""
    render: bool | None = None
    """Render the camera (None: as ``visland fly`` does, only for a vision policy)."""
    out: str | None = None
    """Run folder for both processes' logs (None: a temporary folder, removed after)."""
    repeats: int = 1
    """Times the pair flies the episodes (each run its own pair of processes): the figures are
    the median run's (by real-time factor), ``runs`` has every run's and the best and median
    (a busy machine slows some runs; the best is the least disturbed)."""


def _in_process(cfg: SitlBenchConfig, frames: int, render: bool) -> float:
    """Wall seconds per control period of the bare simulator, flown by the privileged
    CascadeLander on episode 0's initial state (the floor of the pair's cost)."""
    from expert.cascade import CascadeLander
    from sitl_sim.config import load_sim, load_vehicle
    from sitl_sim.scenario import InitialStateSampler, load_scenario
    from sitl_sim.simulator import Simulator

    vehicle = load_vehicle()
    scenario = load_scenario(cfg.scenario)
    sim_cfg = load_sim().with_planet(scenario.world)
    sim = Simulator(vehicle, sim_cfg, render=render)
    pilot = CascadeLander(vehicle, sim_cfg.planet)
    try:
        sim.reset(InitialStateSampler(scenario, cfg.seed).sample(0), cfg.seed)
        t0 = time.perf_counter()
        for k in range(frames):
            gt = sim.ground_truth()
            sim.observe(frame_id=k, truth=gt)
            sim.step(pilot.command(gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz))
        return (time.perf_counter() - t0) / frames
    finally:
        sim.close()


def _process(report: dict[str, Any], frames: int) -> dict[str, Any]:
    """One process's :meth:`LoopPerf.report`, with the shares the bench prints and each
    part's milliseconds per frame."""
    shares = report["shares"]
    parts = report["parts_s"]
    per_frame = 1e3 / frames if frames else 0.0
    return {
        "window_wall_s": report["window_wall_s"],
        "window_cpu_s": report["window_cpu_s"],
        "cpu_ms_per_frame": report["window_cpu_s"] * per_frame,
        "shares": {
            "physics": shares["physics"],
            "render": shares["render"],
            "policy": shares["policy"],
            "encode_decode": sum(shares[k] for k in _ENCODE_DECODE),
            "wait": shares["wait"],
            "other": shares["other"],
        },
        "parts_shares": shares,
        "parts_ms_per_frame": {k: v * per_frame for k, v in parts.items()},
        "counts": report["counts"],
    }


def _fly(cfg: SitlBenchConfig, out: Path) -> dict[str, Any]:
    from tools.cli_args import config_from_args
    from training.exec.fly import FlyConfig, FlyError, fly

    runtime = ("--runtime", cfg.runtime) if Path(cfg.policy).is_file() else ()
    # the bench's policy, episodes, seed, scenario and render
    report = fly(
        config_from_args(FlyConfig, cfg, progress=False, out=str(out), companion_args=runtime)
    )
    sitl = parse_perf_line((out / "sitl.log").read_text(errors="replace"))
    try:
        companion = json.loads((out / "companion.json").read_text()).get("perf")
    except (OSError, ValueError):
        companion = None
    if sitl is None or companion is None:
        missing = "the SITL's perf line" if sitl is None else "the companion's perf report"
        raise FlyError(f"{out}: {missing} is missing (a process stopped before its exit?)")
    return {"fly": report, "sitl": sitl, "companion": companion}


def bench_sitl(cfg: SitlBenchConfig | None = None) -> dict[str, Any]:
    """Fly the pair, then time the in-process floor; returns the figures (module docstring).

    Raises:
        FlyError: a process failed, or did not report its counters.
    """
    cfg = cfg or SitlBenchConfig()
    if cfg.episodes < 1:
        raise ValueError(f"episodes = {cfg.episodes}; expected >= 1")
    if cfg.repeats < 1:
        raise ValueError(f"repeats = {cfg.repeats}; expected >= 1")
    runs = []
    for k in range(cfg.repeats):
        if cfg.out is None:
            with tempfile.TemporaryDirectory(prefix="visland_bench_sitl_") as tmp:
                runs.append(_fly(cfg, Path(tmp)))
        else:
            out = Path(cfg.out) if cfg.repeats == 1 else Path(cfg.out) / f"run{k}"
            runs.append(_fly(cfg, out))
    figures = [_run_figures(run) for run in runs]
    order = sorted(range(len(runs)), key=lambda i: figures[i]["realtime_factor"])
    median = order[len(order) // 2]  # of an even count, the better of the middle two
    run = runs[median]
    sitl, companion, report = run["sitl"], run["companion"], run["fly"]
    frames = int(sitl["counts"].get("frames", 0))
    sim_s = sitl["counts"].get("sim_s", 0.0)
    wall = sitl["window_wall_s"]
    cpu = sitl["window_cpu_s"] + companion["window_cpu_s"]
    from sitl_sim.config import load_sim
    from training.exec.fly import policy_is_privileged

    render = cfg.render if cfg.render is not None else not policy_is_privileged(cfg.policy)

    control_dt = load_sim().control_dt_s
    floor = _in_process(cfg, max(frames, 10), render)
    rtf = sim_s / wall if wall > 0 else 0.0
    floor_rtf = control_dt / floor
    return {
        "config": asdict(cfg),
        "render": render,
        "success_rate": report.summary.success_rate,
        "flight_sim_s": sim_s,
        "frames": frames,
        "realtime_factor": rtf,
        "ms_per_frame": 1e3 * wall / frames if frames else 0.0,
        "realtime_factor_cpu": sim_s / cpu if cpu > 0 else 0.0,
        "realtime_factor_end_to_end": sim_s / report.wall_s,
        "sitl": _process(sitl, frames),
        "companion": _process(companion, frames),
        "in_process": {
            "ms_per_frame": 1e3 * floor,
            "realtime_factor": floor_rtf,
            "pilot": "CascadeLander (privileged, in process)",
        },
        "vs_in_process": rtf / floor_rtf,
        "runs": {
            "median_run": median,
            "best_run": order[-1],
            "each": figures,
            **{
                key: {
                    "best": figures[order[-1]][key],
                    "median": figures[median][key],
                }
                for key in figures[0]
            },
        },
    }


def _run_figures(run: dict[str, Any]) -> dict[str, float]:
    """One run's headline figures (``runs`` of :func:`bench_sitl`)."""
    sitl, companion = run["sitl"], run["companion"]
    frames = int(sitl["counts"].get("frames", 0))
    sim_s, wall = sitl["counts"].get("sim_s", 0.0), sitl["window_wall_s"]
    cpu = sitl["window_cpu_s"] + companion["window_cpu_s"]
    return {
        "realtime_factor": sim_s / wall if wall > 0 else 0.0,
        "ms_per_frame": 1e3 * wall / frames if frames else 0.0,
        "realtime_factor_cpu": sim_s / cpu if cpu > 0 else 0.0,
        "sitl_cpu_ms_per_frame": 1e3 * sitl["window_cpu_s"] / frames if frames else 0.0,
        "companion_cpu_ms_per_frame": 1e3 * companion["window_cpu_s"] / frames if frames else 0.0,
    }


def format_sitl_bench(res: dict[str, Any]) -> str:
    """The human-readable lines of a :func:`bench_sitl` result."""
    cfg = res["config"]
    lines = [
        f"SITL + companion in lockstep ({cfg['policy']}, {cfg['episodes']} episodes, "
        f"{res['flight_sim_s']:.1f} s of flight, {res['frames']} frames): "
        f"{res['realtime_factor']:.1f}x real time ({res['ms_per_frame']:.2f} ms per frame); "
        f"{res['realtime_factor_cpu']:.1f}x on CPU time; "
        f"{res['realtime_factor_end_to_end']:.1f}x end to end",
        f"in-process simulator, same run: {res['in_process']['ms_per_frame']:.2f} ms per frame "
        f"({res['in_process']['realtime_factor']:.1f}x) -> the pair at "
        f"{100 * res['vs_in_process']:.0f} % of it",
    ]
    runs = res.get("runs")
    if runs is not None and len(runs["each"]) > 1:
        rtf, ms = runs["realtime_factor"], runs["ms_per_frame"]
        lines.append(
            f"{len(runs['each'])} runs: best {rtf['best']:.1f}x ({ms['best']:.2f} ms per frame), "
            f"median {rtf['median']:.1f}x ({ms['median']:.2f} ms per frame); the figures here "
            "are the median run's"
        )
    for name in ("sitl", "companion"):
        p = res[name]
        shares = ", ".join(f"{k} {100 * v:.0f} %" for k, v in p["shares"].items())
        lines.append(f"{name}: {shares}; CPU {p['cpu_ms_per_frame']:.2f} ms per frame")
    return "\n".join(lines)


if __name__ == "__main__":
    result = bench_sitl()
    print(format_sitl_bench(result), file=sys.stderr)
    print(json.dumps(result, indent=2))
