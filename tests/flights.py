"""Flights for the tests: the low start (:data:`LOW_INITIAL_STATE`), the MAVLink SITL on a
thread with a client beside it (:func:`sitl_with_client`), the scripted privileged pilot that
lands it (:func:`fly_cascade`), and the SITL and the companion as processes on loopback
(:func:`sitl_command`, :func:`companion_command`, :class:`Processes`).

Every SITL started here is stopped even when the test fails; every wait has a timeout.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from expert.cascade import CascadeLander
from sitl_sim.autopilot.px4 import MavResult
from sitl_sim.mavlink.config import SitlConfig
from sitl_sim.mavlink.sitl import MavlinkSitl
from tools.sitl_client import ClientTimeout, SitlClient
from training.exec.fly import FlyConfig, fly, free_udp_port

if TYPE_CHECKING:
    from training.reports import FlyReport

REPO = Path(__file__).resolve().parent.parent

__all__ = [
    "LOW_INITIAL_STATE",
    "Ports",
    "Processes",
    "SitlThread",
    "companion_command",
    "fly_cascade",
    "fly_quietly",
    "free_ports",
    "sitl_command",
    "sitl_with_client",
]


LOW_INITIAL_STATE = """
roll_pitch_deg = [-1.5, 1.5]
yaw_deg = [-180.0, 180.0]
north_east_m = [-1.0, 1.0]
altitude_m = [5.0, 6.0]
vel_north_east_m_s = [-0.2, 0.2]
vel_down_m_s = [0.0, 0.2]
rate_rad_s = [0.0, 0.0]
"""
"""``[initial_state]`` keys of a short flight: 5-6 m above the pad, nearly level and still
(a landing of a few simulated seconds)."""


class Ports(NamedTuple):
    """The SITL's loopback UDP ports: MAVLink (it binds), the companion's (it sends to), the
    camera's (it sends frames to)."""

    mavlink: int
    remote: int
    camera: int


def free_ports() -> Ports:
    """Three free loopback UDP ports."""
    return Ports(free_udp_port(), free_udp_port(), free_udp_port())


class SitlThread:
    """A SITL running on a thread; ``finish`` joins it and re-raises whatever it raised."""

    def __init__(self, sitl: MavlinkSitl) -> None:
        self.sitl = sitl
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True, name="sitl")
        self.thread.start()

    def _run(self) -> None:
        try:
            self.sitl.run()
        except BaseException as exc:  # re-raised in the test thread by finish()
            self.error = exc

    def finish(self, timeout_s: float = 30.0) -> list:
        """The episode results once the SITL has ended on its own (within ``timeout_s``)."""
        self.thread.join(timeout_s)
        if self.thread.is_alive():
            self.sitl.stop()
            self.thread.join(10)
            raise AssertionError(f"SITL still running after {timeout_s} s")
        if self.error is not None:
            raise self.error
        return self.sitl.results

    def stop(self) -> None:
        self.sitl.stop()
        self.thread.join(10)
        assert not self.thread.is_alive(), "SITL thread did not stop"


@contextmanager
def sitl_with_client(ports: Ports, cfg: SitlConfig) -> Iterator[tuple[SitlClient, SitlThread]]:
    """A client on ``ports`` and the SITL of ``cfg`` on a thread; on the way out the SITL is
    stopped and what it raised is raised here (unless the test already failed)."""
    with SitlClient(("127.0.0.1", ports.mavlink), ports.remote, ports.camera) as client:
        runner = SitlThread(MavlinkSitl(cfg))
        try:
            yield client, runner
        finally:
            runner.stop()
        if runner.error is not None:
            raise runner.error


def fly_cascade(
    client: SitlClient,
    runner: SitlThread,
    timeout_s: float = 30.0,
    max_delay_s: float = 0.0,
) -> list[int]:
    """A privileged scripted pilot (CascadeLander on ODOMETRY) until the SITL thread ends: three
    hover setpoints, OFFBOARD, then the lander's command for each frame, stamped with the
    frame's time (as the companion answers). Each answer is delayed by up to ``max_delay_s``
    (uniform, seeded). Returns the ids of the frames it answered, in order."""
    sitl = runner.sitl
    rng = np.random.default_rng(11)
    lander = CascadeLander(sitl.vehicle, sitl.sim_cfg.planet)
    hover = sitl.params.mpc_thr_hover
    deadline = time.monotonic() + timeout_s
    answered: list[int] = []
    while time.monotonic() < deadline:
        try:
            frame = client.next_frame(0.2)
        except ClientTimeout:
            if not runner.thread.is_alive():
                return answered
            continue
        n = len(answered)
        answered.append(frame.frame_id)
        if n < 3:
            client.setpoint(hover, (0.0, 0.0, 0.0), frame.time_us // 1000)
            if n == 2:
                assert client.set_offboard() == MavResult.ACCEPTED
        else:
            gt = client.truth_at(frame.time_us)
            if max_delay_s > 0:
                time.sleep(rng.uniform(0.0, max_delay_s))
            client.command(
                lander.command(gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz), frame.time_us // 1000
            )
    raise AssertionError(f"flight not over after {timeout_s} s")


def fly_quietly(out: str | Path, **fields: Any) -> FlyReport:
    """``visland fly`` in process (:func:`training.exec.fly.fly`) into the run folder ``out``,
    without a progress bar; ``fields``: the rest of its :class:`~training.exec.fly.FlyConfig`."""
    return fly(FlyConfig(out=str(out), progress=False, **fields))


def sitl_command(ports: Ports, log_dir: str | Path, *extra: str, max_wall_s: int = 90) -> list[str]:
    """``python -m sitl_sim.mavlink`` on loopback ``ports`` with no ground-station link, logging
    to ``log_dir``, ending after ``max_wall_s`` of wall time at most; then ``extra``."""
    return [
        sys.executable,
        "-m",
        "sitl_sim.mavlink",
        "--mavlink-port",
        str(ports.mavlink),
        "--remote-port",
        str(ports.remote),
        "--camera-port",
        str(ports.camera),
        "--no-gcs",
        "--log-dir",
        str(log_dir),
        "--max-wall-s",
        str(max_wall_s),
        *extra,
    ]


def companion_command(
    remote_port: int,
    camera_port: int,
    log_dir: str | Path,
    *extra: str,
    policy: str = "expert",
    max_wall_s: int = 90,
) -> list[str]:
    """``python -m training.companion_process`` flying ``policy`` with the simulator's flight
    settings (:func:`training.companion_process.sim_companion_args`), listening for the SITL on
    ``remote_port`` and its camera on ``camera_port``, logging to ``log_dir``, ending after
    ``max_wall_s`` of wall time at most; then ``extra``."""
    from training.companion_process import sim_companion_args

    return [
        sys.executable,
        "-m",
        "training.companion_process",
        *sim_companion_args(),
        "--policy",
        policy,
        "--connect",
        f"udpin:127.0.0.1:{remote_port}",
        "--camera",
        f"udp:127.0.0.1:{camera_port}",
        "--log-dir",
        str(log_dir),
        "--max-wall-s",
        str(max_wall_s),
        *extra,
    ]


class Processes:
    """Subprocesses of one test, stopped by PID at teardown (SIGTERM, then SIGKILL)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: list[subprocess.Popen] = []

    def start(self, name: str, command: list[str]) -> subprocess.Popen:
        """Runs ``command`` (a whole command line) from the repository, its stdout and stderr
        in ``<name>.out`` and ``<name>.err``."""
        err = (self.tmp / f"{name}.err").open("w")
        out = (self.tmp / f"{name}.out").open("w")
        proc = subprocess.Popen(command, cwd=REPO, stdout=out, stderr=err)
        proc.name = name  # type: ignore[attr-defined]
        self.procs.append(proc)
        return proc

    def text(self, name: str) -> str:
        return (self.tmp / f"{name}.err").read_text(errors="replace")

    def wait_text(self, name: str, pattern: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if re.search(pattern, self.text(name)):
                return
            time.sleep(0.05)
        raise AssertionError(f"{name}: no {pattern!r} within {timeout_s} s:\n{self.text(name)}")

    def stop_all(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
