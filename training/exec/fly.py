"""``visland fly``: the SITL and the companion as two processes over UDP, N episodes, eval JSON.

The SITL (``python -m sitl_sim.mavlink``) flies episodes ``0..N-1`` of ``seed``; the
companion (``python -m training.companion_process``) flies each through MAVLink — pre-stream,
OFFBOARD, one command per camera frame, touchdown, disarm. Results are the SITL's own
(``/episode/result`` of its per-episode flight logs: ground truth at first contact, the same
``sitl_sim.metrics`` as in-process ``eval``), so ``fly`` and ``eval`` agree on definitions; the
JSON is ``eval``'s with ``transport = "mavlink"`` plus the companion's latency figures.

Both processes are always stopped (SIGTERM, then SIGKILL, by PID) — on success, on failure
and on Ctrl-C. Ports are picked free per run, so runs can go side by side.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from companion.contract.records import ABSENT, EpisodeResultRecord
from companion.contract.topics import TOPIC_RESULT
from companion.flightlog import read_log
from companion.record import latency_stats
from sitl_sim.config import load_sim
from sitl_sim.metrics import EpisodeResult
from training.companion_process import sim_companion_args
from training.exec.transport import Transport
from training.provenance import REPO, SHIPPED_MODEL
from training.reports import EpisodeRow, FlyReport, LandingSummary
from training.seeds import EVAL_SEED

__all__ = [
    "FlyConfig",
    "FlyError",
    "fly",
    "fly_report",
    "fly_run",
    "free_udp_port",
    "policy_is_privileged",
    "sitl_log_name",
]


class FlyError(RuntimeError):
    """A process of the run failed (names which, with the tail of its output)."""


@dataclass(frozen=True)
class FlyConfig:
    """Options of ``visland fly``."""

    policy: str = "expert"
    """``expert`` | ``cascade`` | a checkpoint path (``untrained`` for benchmarks)."""
    episodes: int = 20
    seed: int = EVAL_SEED
    first_episode: int = 0
    """Fly episodes ``first_episode .. first_episode + episodes - 1`` of ``seed``."""
    scenario: str | None = None
    realtime: bool = False
    """Real time (the SITL follows the wall clock) instead of lockstep."""
    render: bool | None = None
    """Render the camera (None: only for vision policies; privileged ones do not look)."""
    out: str | None = None
    """Run folder for the SITL and companion logs (None: a temporary folder)."""
    sitl_log_dir: str | None = None
    """Folder for the SITL's flight logs (None: ``<out>/sitl``)."""
    timeout_s: float | None = None
    """Wall-clock limit of the whole run (None: from the episode count)."""
    companion_mode: str = "offboard"
    """``offboard`` (the policy flies) or ``landing-target`` (the companion streams
    LANDING_TARGET from the policy's camera estimator; the SITL's AUTO.PRECLAND lands)."""
    companion_args: tuple[str, ...] = ()
    sitl_args: tuple[str, ...] = ()
    scene: bool = False
    """After the run, write the live view's picture into every log of it (``visland log
    scene``: annotations, 3D scene, transforms, time series, events), so each opens in
    Foxglove with ``docs/foxglove/visland.json`` as a live flight does; the flights pay
    nothing for it. A vision checkpoint is run again on the SITL's logs for the CNN's bearing
    and the estimate (the companion's logs run their own)."""
    sitl_command: tuple[str, ...] = ()
    """The command that starts the SITL, before its flags (default: this Python, ``-m
    sitl_sim.mavlink``); e.g. one that sets a resource limit first."""
    companion_command: tuple[str, ...] = ()
    """The command that starts the companion, before its flags (default: this Python,
    ``-m training.companion_process``); e.g. another install's ``python -I .../visland
    companion``, to fly a board's environment against this SITL."""
    companion_cwd: str | None = None
    """The companion's working directory (None: the repository); e.g. a folder outside it, to
    show that an installed companion finds its model and config through its package."""
    progress: bool = True
    env: dict[str, str] = field(default_factory=dict)
    ports: tuple[int, int, int] | None = None
    """Loopback UDP ports (SITL MAVLink, companion MAVLink, camera); None: free ones."""
    autopilot: str = "px4"
    """The SITL's autopilot profile and the companion's (``px4`` or ``ardupilot``)."""
    sitl_params: tuple[str, ...] = ()
    """``NAME=VALUE`` parameters for the SITL's ``--param``, after the profile's setup
    (:func:`setup_params`), so they win."""
    live: str = ""
    """``[HOST:]PORT``: the companion serves the live view there (the SITL then sends its truth
    as ODOMETRY, drawn beside the estimate); '' = off."""
    monitor: Callable[[int, int], None] | None = field(default=None, compare=False)
    """Called about every 0.5 s while the pair flies with ``(companion pid, episodes ended so
    far)`` (``visland soak`` samples the companion's memory and descriptors with it)."""


AUTOPILOTS = ("px4", "ardupilot")


def setup_params(autopilot: str, companion_mode: str) -> tuple[str, ...]:
    """The parameters a vehicle of this profile is configured with once, before a companion
    can fly it (``--param`` of the SITL): ArduPilot needs GUID_OPTIONS bit 3 for thrust to be
    thrust, and PLND_ENABLED = 1 with PLND_TYPE = 1 (MAVLink) to land on LANDING_TARGET. PX4
    needs nothing."""
    if autopilot != "ardupilot":
        return ()
    if companion_mode == "landing-target":
        return ("PLND_ENABLED=1", "PLND_TYPE=1")
    return ("GUID_OPTIONS=8",)


COMPANION_MODES = ("offboard", "landing-target")
DEFAULT_VISION_POLICY = str(SHIPPED_MODEL)
"""The shipped vision policy (:data:`training.provenance.SHIPPED_MODEL`) as a
:attr:`FlyConfig.policy`: what ``--companion-mode landing-target`` flies by default."""

_handed_out: set[int] = set()
_ports_lock = threading.Lock()


def _planet_args(cfg: FlyConfig) -> list[str]:
    """``--planet`` for a privileged pilot of the companion shell (it models the world the
    SITL's scenario flies: the MPC on Mars with Earth's gravity would hover, never land)."""
    if cfg.policy not in ("expert", "cascade") or cfg.companion_command or not cfg.scenario:
        return []
    from sitl_sim.scenario import load_scenario

    return ["--planet", load_scenario(cfg.scenario).world.name]


def free_udp_port() -> int:
    """A UDP port free on 127.0.0.1 now (never the same twice in this process)."""
    with _ports_lock:
        return _free_udp_port()


def _free_udp_port() -> int:
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port not in _handed_out:
            _handed_out.add(port)
            return port


def policy_is_privileged(policy: str) -> bool:
    if policy in ("expert", "cascade", "untrained-privileged"):
        return True
    if policy == "untrained":
        return False
    from companion.policy_net import load_policy

    return load_policy(policy).privileged


def _stop(*procs: subprocess.Popen | None, grace_s: float = 5.0) -> None:
    """SIGTERM to each (in order, without waiting in between), then SIGKILL what is still
    running after ``grace_s``: by PID, only our own children. Signalling all before waiting
    keeps a Ctrl-C to at most ``grace_s`` however many children shut down slowly."""
    alive = [p for p in procs if p is not None and p.poll() is None]
    for proc in alive:
        proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for proc in alive:
        try:
            proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


def sitl_log_name(seed: int, index: int) -> str:
    """The SITL's flight log of episode ``index`` of ``seed`` (``sitl_sim.mavlink.sitl``)."""
    return f"sitl_seed{seed}_ep{index:04d}.mcap"


def _results(sitl_dir: Path, seed: int, indices: range) -> list[EpisodeRow]:
    """The row of each finished episode: its ``/episode/result`` record (the SITL's log), with
    the impaired link's counts where the run had one."""
    out = []
    for i in indices:
        path = sitl_dir / sitl_log_name(seed, i)
        if not path.exists():
            continue
        messages = read_log(path, topics=[TOPIC_RESULT]).topic(TOPIC_RESULT)
        if not messages:
            continue
        rec = EpisodeResultRecord.from_dict(messages[-1])
        if rec.aborted is True:
            continue
        impairment = None if rec.link_impairment is ABSENT else dict(rec.link_impairment)
        result = EpisodeResult.read(messages[-1])
        out.append(
            EpisodeRow(
                seed=seed, episode=i, **result.to_dict(), log=str(path), link_impairment=impairment
            )
        )
    return out


def fly(cfg: FlyConfig) -> FlyReport:
    """Run the episodes; returns the eval-style report (``transport = "mavlink"``).

    Raises:
        FlyError: a process failed or the run timed out (both processes stopped first).
    """
    if cfg.episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {cfg.episodes}")
    if cfg.companion_mode not in COMPANION_MODES:
        raise ValueError(
            f"companion_mode = {cfg.companion_mode!r}; expected one of {COMPANION_MODES}"
        )
    if cfg.autopilot not in AUTOPILOTS:
        raise ValueError(f"autopilot = {cfg.autopilot!r}; expected one of {AUTOPILOTS}")
    params = setup_params(cfg.autopilot, cfg.companion_mode) + tuple(cfg.sitl_params)
    privileged = policy_is_privileged(cfg.policy)
    if privileged and cfg.companion_mode == "landing-target":
        raise ValueError(
            f"--companion-mode landing-target needs a vision checkpoint (camera + pad "
            f"estimator), not {cfg.policy!r}: e.g. --policy {DEFAULT_VISION_POLICY}"
        )
    render = (not privileged) if cfg.render is None else cfg.render
    out = Path(cfg.out) if cfg.out else Path(tempfile.mkdtemp(prefix="visland_fly_"))
    sitl_dir = Path(cfg.sitl_log_dir) if cfg.sitl_log_dir else out / "sitl"
    comp_dir = out / "companion"
    out.mkdir(parents=True, exist_ok=True)
    mav, remote, cam = cfg.ports or (free_udp_port(), free_udp_port(), free_udp_port())
    episode_s = load_sim().episode_timeout_s
    timeout_s = cfg.timeout_s or 60.0 + cfg.episodes * (episode_s * (1.2 if cfg.realtime else 0.6))
    sitl_cmd = [
        *(cfg.sitl_command or (sys.executable, "-m", "sitl_sim.mavlink")),
        "--mavlink-port",
        str(mav),
        "--remote-port",
        str(remote),
        "--camera-port",
        str(cam),
        "--no-gcs",
        "--episodes",
        str(cfg.episodes),
        "--seed",
        str(cfg.seed),
        "--first-episode",
        str(cfg.first_episode),
        "--log-dir",
        str(sitl_dir),
        "--max-wall-s",
        str(timeout_s),
        "--groundtruth" if privileged or cfg.live else "--no-groundtruth",
        "--render" if render else "--no-render",
        "--no-lockstep" if cfg.realtime else "--lockstep",
        *(["--scenario", cfg.scenario] if cfg.scenario else []),
        "--autopilot",
        cfg.autopilot,
        *(["--param", ",".join(params)] if params else []),
        *cfg.sitl_args,
    ]
    comp_cmd = [
        *(cfg.companion_command or (sys.executable, "-m", "training.companion_process")),
        *sim_companion_args(),  # the simulator's flight settings over the hardware defaults
        "--policy",
        cfg.policy,
        *_planet_args(cfg),
        "--connect",
        f"udpin:127.0.0.1:{remote}",
        "--camera",
        f"udp:127.0.0.1:{cam}",
        "--mode",
        cfg.companion_mode,
        *(["--autopilot", cfg.autopilot] if cfg.autopilot != "px4" else []),
        "--flights",
        "0",  # until stopped: the SITL decides when the run is over
        "--log-dir",
        str(comp_dir),
        "--max-wall-s",
        str(timeout_s),
        *(["--live", cfg.live] if cfg.live else []),
        *cfg.companion_args,
    ]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **cfg.env}
    sitl_log, comp_log, comp_out = out / "sitl.log", out / "companion.log", out / "companion.json"
    sitl = comp = None
    t0 = time.monotonic()
    try:
        with sitl_log.open("w") as s_err, comp_log.open("w") as c_err, comp_out.open("w") as c_out:
            # The companion first: its port is bound before the SITL's first HEARTBEAT.
            comp = subprocess.Popen(
                comp_cmd, cwd=cfg.companion_cwd or REPO, stdout=c_out, stderr=c_err, env=env
            )
            sitl = subprocess.Popen(
                sitl_cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=s_err, env=env
            )
            done_shown = -1
            while sitl.poll() is None:
                ended = None
                if cfg.monitor is not None or cfg.progress:
                    ended = sitl_log.read_text(errors="replace").count(" ended: ")
                if cfg.monitor is not None:
                    cfg.monitor(comp.pid, ended)
                if time.monotonic() - t0 > timeout_s + 30:
                    raise FlyError(f"run not finished after {timeout_s + 30:.0f} s")
                if comp.poll() is not None:
                    raise FlyError(
                        f"companion exited with {comp.returncode} while the SITL was still "
                        f"flying:\n{_tail(comp_log)}"
                    )
                if cfg.progress and ended != done_shown:
                    done_shown = ended
                    print(f"fly: {ended}/{cfg.episodes} episodes", file=sys.stderr, flush=True)
                time.sleep(0.5)
            if sitl.returncode != 0:
                raise FlyError(f"SITL exited with {sitl.returncode}:\n{_tail(sitl_log)}")
    finally:
        _stop(comp, sitl)  # SIGTERM: the companion hands back and closes its log, then the SITL
    wall = time.monotonic() - t0
    rows = _results(sitl_dir, cfg.seed, range(cfg.first_episode, cfg.first_episode + cfg.episodes))
    if len(rows) != cfg.episodes:
        cut = sum(
            1 for p in sitl_dir.glob("*.mcap") if read_log(p, topics=[TOPIC_RESULT]).truncated
        )
        raise FlyError(
            f"{len(rows)} of {cfg.episodes} episodes finished"
            + (f" ({cut} SITL logs cut before their result: a full disk?)" if cut else "")
            + f"; SITL log:\n{_tail(sitl_log)}\ncompanion log:\n{_tail(comp_log)}"
        )
    try:
        companion_report = json.loads(comp_out.read_text() or "{}")
    except ValueError:
        companion_report = {}
    flights = companion_report.get("flights", [])
    if cfg.scene:
        _with_scenes(cfg, [Path(str(r.log)) for r in rows], sorted(comp_dir.glob("*.mcap")))
    return fly_report(
        cfg,
        rows,
        sorted(comp_dir.glob("*.mcap")),
        {
            k: sum(1 for f in flights if f.get("result") == k)
            for k in sorted({f.get("result") for f in flights})
        },
        wall_s=wall,
        out=str(out),
    )


def _with_scenes(cfg: FlyConfig, sitl_logs: list[Path], companion_logs: list[Path]) -> None:
    """:attr:`FlyConfig.scene`: each log with the live view's picture in it (as it was where
    foxglove-sdk is missing or a log cannot be drawn: said on stderr)."""
    from companion.live.scene_log import add_scenes

    vision = cfg.policy if Path(cfg.policy).is_file() else None
    add_scenes([(p, vision) for p in sitl_logs] + [(p, None) for p in companion_logs], "fly")


def fly_report(
    cfg: FlyConfig,
    rows: list[EpisodeRow],
    companion_logs: list[Path],
    companion_flights: dict[str, int],
    **where: Any,
) -> FlyReport:
    """The report of :func:`fly` and ``training.exec.fly_many`` (``where``: ``wall_s``, ``out``
    and, for many runs, ``instances``, ``runs``, ``backend``)."""
    return FlyReport(
        policy=cfg.policy,
        transport=Transport.MAVLINK.value,
        seed=cfg.seed,
        scenario=cfg.scenario or "configs/scenario.toml",
        realtime=cfg.realtime,
        companion_mode=cfg.companion_mode,
        autopilot=cfg.autopilot,
        episodes=len(rows),
        summary=LandingSummary.of([r.result() for r in rows]),
        latency_ms=latency_stats(companion_logs),
        companion_flights=companion_flights,
        link_impairment=_link_totals(rows),
        per_episode=tuple(rows),
        **where,
    )


def _link_totals(rows: list[EpisodeRow]) -> dict[str, dict[str, int]] | None:
    """``{stream: {counter: sum}}`` over the episodes that had an impaired link (None when
    none had)."""
    totals: dict[str, dict[str, int]] = {}
    for row in rows:
        for stream, counts in (row.link_impairment or {}).get("streams", {}).items():
            acc = totals.setdefault(stream, {})
            for key, value in counts.items():
                acc[key] = acc.get(key, 0) + value
    return totals or None


def fly_run(cfg: FlyConfig, first: int, count: int, out: Path, sitl_dir: Path) -> FlyReport:
    """Episodes ``first .. first + count - 1`` of ``cfg.seed`` through one SITL + companion
    pair: the pair's files in ``out/ep<first>/``, the SITL's flight logs in ``sitl_dir``
    (one unit of ``training.exec.fly_many``'s work, on whichever backend runs it).

    Raises:
        FlyError: as :func:`fly`.
    """
    return fly(
        replace(
            cfg,
            first_episode=first,
            episodes=count,
            out=str(Path(out) / f"ep{first:04d}"),
            sitl_log_dir=str(sitl_dir),
            timeout_s=None,
            progress=False,
        )
    )
