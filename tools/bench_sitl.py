"""``bench sitl``: what the MAVLink/camera path costs on top of the simulator.

In one run, on the same initial state and with the same pilot (the privileged CascadeLander):

1. **in-process**: :class:`~sitl_sim.simulator.Simulator` stepped directly (physics, sensors,
   camera render at 10 Hz) — the floor;
2. **SITL over UDP**: ``python -m sitl_sim.mavlink`` as its own process in lockstep, and a
   scripted pymavlink client here that reads every camera frame and the ground truth (ODOMETRY)
   and answers with SET_ATTITUDE_TARGET.

Printed: the SITL's lockstep real-time factor (flight sim seconds per wall second, take-over to
disarm), wall time per 10 Hz frame for both, and the difference = the per-frame overhead of the
MAVLink/camera/log path (telemetry streams at 50 Hz, their encoding, the flight log, UDP, the
client's decoding). Also the SITL process's own CPU time per frame over the same frames (Linux
``/proc``): unlike wall time it hardly moves when other work shares the machine, so it is the
figure to compare before/after a change.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from expert.cascade import CascadeLander
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.scenario import InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator
from tools.sitl_client import ClientTimeout, SitlClient
from training.exec.fly import free_udp_port
from training.provenance import REPO

__all__ = ["SitlBenchConfig", "bench_sitl"]


@dataclass(frozen=True)
class SitlBenchConfig:
    seed: int = 0
    """Episode 0 of this seed is flown (configs/scenario.toml unless ``scenario``)."""
    scenario: str | None = None
    render: bool = True
    """Render the camera in both runs."""
    log_dir: str | None = None
    """Flight-log folder for the SITL run (None: a temporary folder; logging stays on)."""
    timeout_s: float = 300.0
    """Wall-clock limit for the SITL run."""


def _cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` so far (None where /proc is missing)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _in_process(cfg: SitlBenchConfig, frames: int) -> float:
    """Wall seconds per control period of the bare simulator, flown by the same pilot."""
    vehicle, sim_cfg = load_vehicle(), load_sim()
    scenario = load_scenario(cfg.scenario)
    sim_cfg = sim_cfg.with_planet(scenario.world)
    initial = InitialStateSampler(scenario, cfg.seed).sample(0)
    sim = Simulator(vehicle, sim_cfg, render=cfg.render)
    pilot = CascadeLander(vehicle, sim_cfg.planet)
    try:
        sim.reset(initial, cfg.seed)
        t0 = time.perf_counter()
        for k in range(frames):
            gt = sim.ground_truth()
            sim.observe(frame_id=k, truth=gt)
            sim.step(pilot.command(gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz))
        return (time.perf_counter() - t0) / frames
    finally:
        sim.close()


def _over_udp(cfg: SitlBenchConfig, log_dir: str) -> dict[str, Any]:
    mav_port, remote_port, cam_port = free_udp_port(), free_udp_port(), free_udp_port()
    cmd = [
        sys.executable, "-m", "sitl_sim.mavlink",
        "--mavlink-port", str(mav_port), "--remote-port", str(remote_port),
        "--camera-port", str(cam_port), "--gcs-port", str(free_udp_port()),
        "--gcs-remote-port", str(free_udp_port()), "--seed", str(cfg.seed), "--groundtruth",
        "--log-dir", log_dir, "--max-wall-s", str(cfg.timeout_s),
        "--render" if cfg.render else "--no-render",
    ]  # fmt: skip
    if cfg.scenario:
        cmd += ["--scenario", cfg.scenario]
    vehicle, sim_cfg = load_vehicle(), load_sim()
    scenario = load_scenario(cfg.scenario)
    pilot = CascadeLander(vehicle, scenario.world)
    hover = vehicle.hover_thrust_norm(scenario.world)
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        with SitlClient(("127.0.0.1", mav_port), remote_port, cam_port) as client:
            client.wait_for("HEARTBEAT", 60.0)
            n, flight_frames, t_first, t_last, us_first, us_last = 0, 0, 0.0, 0.0, 0, 0
            cpu_first = cpu_last = None
            deadline = time.monotonic() + cfg.timeout_s
            while time.monotonic() < deadline:
                try:
                    frame = client.next_frame(0.5)
                except ClientTimeout:
                    if proc.poll() is not None:
                        break
                    continue
                if n < 3:  # pre-stream, then OFFBOARD (the frozen HOLD phase is not timed)
                    client.setpoint(hover, (0.0, 0.0, 0.0), frame.time_us // 1000)
                    if n == 2 and client.set_offboard() != 0:
                        raise RuntimeError("SITL refused OFFBOARD")
                    n += 1
                    continue
                gt = client.truth_at(frame.time_us)
                if flight_frames == 0:
                    t_first, us_first = time.perf_counter(), frame.time_us
                    cpu_first = _cpu_s(proc.pid)
                client.command(
                    pilot.command(gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz),
                    frame.time_us // 1000,
                )
                t_last, us_last = time.perf_counter(), frame.time_us
                cpu_last = _cpu_s(proc.pid)
                flight_frames += 1
                n += 1
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    if proc.returncode != 0 or flight_frames < 10:
        raise RuntimeError(
            f"SITL run failed (rc {proc.returncode}, {flight_frames} frames): "
            f"{proc.stderr.read().decode()[-2000:] if proc.stderr else ''}"
        )
    wall = t_last - t_first
    sim_s = (us_last - us_first) * 1e-6
    return {
        "frames": flight_frames - 1,
        "sim_s": sim_s,
        "wall_s": wall,
        "s_per_frame": wall / (flight_frames - 1),
        "cpu_s_per_frame": (
            (cpu_last - cpu_first) / (flight_frames - 1)
            if cpu_first is not None and cpu_last is not None
            else None
        ),
        "control_period_s": sim_cfg.control_dt_s,
    }


def bench_sitl(cfg: SitlBenchConfig | None = None) -> dict[str, Any]:
    """Run both measurements and print/return the figures (see the module docstring)."""
    cfg = cfg or SitlBenchConfig()
    if cfg.log_dir is None:
        import tempfile

        with tempfile.TemporaryDirectory(prefix="visland_bench_sitl_") as tmp:
            udp = _over_udp(cfg, tmp)
    else:
        udp = _over_udp(cfg, cfg.log_dir)
    bare = _in_process(cfg, udp["frames"])
    result = {
        "config": asdict(cfg),
        "frames": udp["frames"],
        "flight_sim_s": udp["sim_s"],
        "sitl_lockstep_realtime_factor": udp["sim_s"] / udp["wall_s"],
        "sitl_ms_per_frame": 1e3 * udp["s_per_frame"],
        "in_process_ms_per_frame": 1e3 * bare,
        "in_process_realtime_factor": udp["control_period_s"] / bare,
        "overhead_ms_per_frame": 1e3 * (udp["s_per_frame"] - bare),
        "sitl_cpu_ms_per_frame": (
            1e3 * udp["cpu_s_per_frame"] if udp["cpu_s_per_frame"] is not None else None
        ),
    }
    print(
        f"SITL lockstep over UDP: {result['sitl_lockstep_realtime_factor']:.1f}x real time "
        f"({result['sitl_ms_per_frame']:.2f} ms per 10 Hz frame, {result['frames']} frames); "
        f"in-process simulator: {result['in_process_ms_per_frame']:.2f} ms per frame "
        f"({result['in_process_realtime_factor']:.1f}x); MAVLink/camera/log overhead "
        f"{result['overhead_ms_per_frame']:.2f} ms per frame; SITL process CPU "
        f"{result['sitl_cpu_ms_per_frame'] or float('nan'):.2f} ms per frame",
        file=sys.stderr,
    )
    return result


if __name__ == "__main__":
    print(json.dumps(bench_sitl(), indent=2))
