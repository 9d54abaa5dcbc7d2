"""The companion process: ``python -m companion`` / ``visland companion``.

One thread, one loop: ``select`` on the MAVLink port and the camera, feed the telemetry store,
answer each camera frame with one command (or, in shadow mode, only log it), run the timers of
the state machine (:mod:`companion.offboard`). One MCAP log per flight
(:mod:`companion.record`). SIGINT/SIGTERM hand control back (LAND or HOLD, ``on_exit``) and close
the log; the process then prints a JSON report on stdout.

Configuration: :class:`CompanionConfig` — defaults, then a TOML file (``--config``, table
``[companion]``, e.g. ``configs/companion.toml``), then command-line flags. The flight and safety
settings' defaults are those of :class:`~companion.flight.OffboardConfig` and
:class:`~companion.safety.SafetyConfig` (typed there, once); :meth:`CompanionConfig.offboard_config`
and :meth:`CompanionConfig.safety_config` build them.
``--replay LOG`` runs a recorded log through the policy instead (shadow, no link) and reports
how far the recomputed commands are from the recorded ones.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import select
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion import options
from companion.camera import CameraError, check_intrinsics, open_camera
from companion.contract.companion_records import CompanionSummaryRecord
from companion.contract.perf import LoopPerf
from companion.files import read_toml
from companion.flight import FlightContext, OffboardConfig
from companion.link import PROFILES, LinkError, MavlinkLink, mavlink
from companion.offboard import FlightController
from companion.options import option, redacted_dict
from companion.runtime import PolicyRuntime
from companion.safety import SafetyConfig, SafetyMonitor
from companion.states import FlightResult, FlightState, TouchdownAction
from companion.telemetry import TelemetryStore

__all__ = [
    "CompanionConfig",
    "CompanionError",
    "add_arguments",
    "config_from_args",
    "main",
    "run",
    "run_from_args",
]

log = logging.getLogger("visland.companion")


class CompanionError(ValueError):
    """A configuration or start-up error (names the file/field and the expected value)."""


_FLIGHT = {f.name: f.default for f in dataclasses.fields(OffboardConfig)}
"""OffboardConfig's defaults: the flight fields below take theirs from here."""
_SAFETY = {f.name: f.default for f in dataclasses.fields(SafetyConfig)}
"""SafetyConfig's defaults (seconds, per-axis tuple): the safety fields below convert them."""


@dataclass(frozen=True)
class CompanionConfig:
    """Everything ``visland companion`` takes; each field is a ``--flag`` and a TOML key."""

    connect: str = option(
        "udpin:127.0.0.1:14540",
        "MAVLink connection: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, /dev/ttyX or "
        "serial:/dev/ttyX:BAUD",
    )
    baud: int = option(921_600, "serial baud rate")
    autopilot: str = option("px4", "autopilot profile", choices=tuple(PROFILES))
    camera: str = option(
        "udp:127.0.0.1:5600", "camera: udp:HOST:PORT (SITL), opencv:DEVICE|FILE|PIPELINE, mcap:LOG"
    )
    camera_fx_px: float | None = option(None, "real camera: focal length fx in pixels", float)
    camera_hfov_deg: float | None = option(
        None, "real camera: horizontal FOV (no intrinsics)", float
    )
    camera_cx_px: float | None = option(
        None, "real camera: principal point cx (default: centre)", float
    )
    camera_cy_px: float | None = option(
        None, "real camera: principal point cy (default: centre)", float
    )
    camera_rotate_deg: int = option(0, "real camera: rotation (CCW) so image top = body forward")
    camera_rate_hz: float = option(
        10.0, "real camera: frames handed to the policy per second (its 10 Hz control rate)"
    )
    mode: str = option(
        "offboard",
        "offboard: fly the policy's commands (SET_ATTITUDE_TARGET); landing-target: run only "
        "its camera pad estimator, stream LANDING_TARGET and let the autopilot's precision "
        "land (PX4 AUTO.PRECLAND, ArduPilot LAND + PLND) fly",
        choices=("offboard", "landing-target"),
    )
    target_timeout_s: float = option(
        1.0, "landing-target mode: stop sending this long after the pad was last seen"
    )
    policy: str = option("", "policy checkpoint (visland companion also takes expert | cascade)")
    runtime: str = option(
        "auto",
        "learned policy backend: onnx (ONNX Runtime on the visland export-onnx graphs beside "
        "the checkpoint; no torch needed), torch, or auto (onnx when onnxruntime is installed "
        "and the export is there, else torch)",
        choices=("auto", "torch", "onnx"),
    )
    torch_threads: int = option(1, "intra-op threads for the policy (torch or ONNX Runtime)")
    shadow: bool = option(
        _FLIGHT["shadow"], "compute and log every command; send no setpoint, no mode change"
    )
    arm: bool = option(
        _FLIGHT["arm"], "arm when disarmed (SITL demo only; on hardware the pilot arms)"
    )
    flights: int = option(1, "flights to fly before exiting (0: until stopped)")
    signing_key: str | None = option(
        None, "MAVLink 2 signing key: 64 hex digits or a passphrase", str
    )
    sysid: int = option(0, "our MAVLink system id (0: the autopilot's)")
    max_age_ms: float = option(
        _SAFETY["max_age_s"] * 1000.0, "failsafe when camera or telemetry is older than this"
    )
    near_ground_m: float = option(_SAFETY["near_ground_m"], "below this, no valid range = failsafe")
    thrust_min: float = option(_SAFETY["thrust_min"], "thrust clamp, low")
    thrust_max: float = option(_SAFETY["thrust_max"], "thrust clamp, high")
    max_rate_rp_rad_s: float = option(_SAFETY["max_rate_rad_s"][0], "roll/pitch rate clamp")
    max_rate_yaw_rad_s: float = option(_SAFETY["max_rate_rad_s"][2], "yaw rate clamp")
    prestream_s: float = option(
        _FLIGHT["prestream_s"], "neutral setpoints streamed before requesting OFFBOARD"
    )
    engage_min_range_m: float = option(
        _FLIGHT["engage_min_range_m"], "engage only above this radar range"
    )
    touchdown_range_m: float = option(
        _FLIGHT["touchdown_range_m"], "radar range at or below which the vehicle is down"
    )
    on_touchdown: str = option(
        _FLIGHT["on_touchdown"].value,
        "after touchdown",
        str,
        choices=tuple(action.value for action in TouchdownAction),
    )
    on_exit: str = option("land", "mode requested on SIGINT/SIGTERM", choices=("land", "hold"))
    hover_thrust: float = option(
        _FLIGHT["hover_thrust"], "neutral thrust if the autopilot does not report it"
    )
    link_timeout_s: float = option(3.0, "no autopilot HEARTBEAT this long = link lost")
    log_dir: str | None = option(
        "runs/companion/flights", "folder for one MCAP log per flight", str
    )
    max_wall_s: float | None = option(None, "exit after this many seconds (safety net)", float)

    def __post_init__(self) -> None:
        if self.flights < 0:
            raise CompanionError(f"flights = {self.flights}; expected >= 0")
        if not (math.isfinite(self.max_age_ms) and self.max_age_ms > 0):
            raise CompanionError(f"max_age_ms = {self.max_age_ms}; expected > 0")
        if self.camera_rotate_deg % 90:
            raise CompanionError(f"camera_rotate_deg = {self.camera_rotate_deg}; a multiple of 90")
        if self.camera.startswith("opencv:"):
            try:
                check_intrinsics(self.camera_fx_px, self.camera_hfov_deg)
            except CameraError as exc:
                raise CompanionError(f"camera {self.camera!r}: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, with the signing key redacted."""
        return redacted_dict(self)

    def safety_config(self) -> SafetyConfig:
        """The safety monitor's limits (milliseconds to seconds, per-axis rate clamp).

        Raises:
            companion.safety.SafetyError: a limit out of range.
        """
        return SafetyConfig(
            max_age_s=self.max_age_ms / 1000.0,
            near_ground_m=self.near_ground_m,
            thrust_min=self.thrust_min,
            thrust_max=self.thrust_max,
            max_rate_rad_s=(
                self.max_rate_rp_rad_s,
                self.max_rate_rp_rad_s,
                self.max_rate_yaw_rad_s,
            ),
        )

    def offboard_config(self) -> OffboardConfig:
        """The state machine's settings (those not set here keep OffboardConfig's defaults).

        Raises:
            ValueError: a setting out of range.
        """
        return OffboardConfig(
            shadow=self.shadow,
            arm=self.arm,
            prestream_s=self.prestream_s,
            engage_min_range_m=self.engage_min_range_m,
            touchdown_range_m=self.touchdown_range_m,
            on_touchdown=self.on_touchdown,  # OffboardConfig makes it a TouchdownAction
            hover_thrust=self.hover_thrust,
        )


def load_toml(path: str | Path) -> dict[str, Any]:
    """The ``[companion]`` table of a TOML file, checked against the config's fields.

    Raises:
        CompanionError: the file is missing or not TOML, or the table is missing or wrong.
    """
    data = read_toml(path, CompanionError)
    table = data.get("companion")
    if not isinstance(table, dict):
        raise CompanionError(f"{path}: expected a [companion] table")
    return options.check_table(table, CompanionConfig, f"{path}: [companion]", CompanionError)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--config``, ``--replay`` and one ``--flag`` per :class:`CompanionConfig` field."""
    parser.add_argument("--config", type=Path, default=None, help="TOML file ([companion] table)")
    parser.add_argument(
        "--replay", type=Path, default=None, help="replay a companion log in shadow mode"
    )
    parser.add_argument("--json", action="store_true", help="(accepted; the report is JSON)")
    options.add_arguments(parser, CompanionConfig, unset_is_none=True)  # None: not given


def config_from_args(args: argparse.Namespace) -> CompanionConfig:
    values: dict[str, Any] = {}
    if args.config is not None:
        values.update(load_toml(args.config))
    values.update(options.values_from_args(args, CompanionConfig))
    if values.get("log_dir") == "":
        values["log_dir"] = None
    return CompanionConfig(**values)


# --------------------------------------------------------------------------- the process


def _open_camera(cfg: CompanionConfig):
    opts: dict[str, Any] = {}
    if cfg.camera.startswith("opencv:"):
        opts = {
            "fx_px": cfg.camera_fx_px,
            "hfov_deg": cfg.camera_hfov_deg,
            "cx_px": cfg.camera_cx_px,
            "cy_px": cfg.camera_cy_px,
            "rotate_deg": cfg.camera_rotate_deg,
            "rate_hz": cfg.camera_rate_hz,
        }
    return open_camera(cfg.camera, **opts)


class Companion:
    """The process: build from a config and a policy, then :meth:`run`; :meth:`stop` from a
    signal handler or another thread."""

    def __init__(self, cfg: CompanionConfig, policy: Any, policy_name: str) -> None:
        from companion.contract.signing import signing_key_bytes

        self.cfg = cfg
        self.runtime = PolicyRuntime(policy, policy_name)
        if self.runtime.privileged:
            log.warning(
                "policy %s is privileged: it needs ODOMETRY ground truth (SITL only)", policy_name
            )
        self.safety = SafetyMonitor(cfg.safety_config())
        self.flight_cfg = cfg.offboard_config()
        self.tracker = None
        if cfg.mode == "landing-target":
            from companion.landing_target import LandingTargetError, PadTracker

            try:
                self.tracker = PadTracker(policy, cfg.target_timeout_s)
            except LandingTargetError as exc:
                raise CompanionError(
                    f"--mode landing-target, policy {policy_name!r}: {exc}"
                ) from None
        error = self.runtime.warm_up()
        if error is not None:
            raise CompanionError(f"policy {policy_name!r} fails on a synthetic hover: {error}")
        self.store = TelemetryStore()
        self.camera = _open_camera(cfg)
        try:
            self.link = MavlinkLink(
                cfg.connect,
                baud=cfg.baud,
                profile=PROFILES[cfg.autopilot],
                sysid=cfg.sysid or None,
                signing_key=signing_key_bytes(cfg.signing_key) if cfg.signing_key else None,
                link_timeout_s=cfg.link_timeout_s,
            )
        except Exception:
            self.camera.close()
            raise
        self._stop = threading.Event()
        self._stop_reason = ""
        self.flight = None
        self.flight_log = None
        self.outcomes: list[dict[str, Any]] = []
        self.link_events: list[str] = []
        self._clock: Callable[[], float] = time.monotonic
        self._requested_streams = False
        self.perf = LoopPerf()
        """Wall time per part of the loop while a flight is in the air (the report's
        ``perf``)."""

    # ------------------------------------------------------------------ plumbing

    def stop(self, reason: str = "stopped") -> None:
        self._stop_reason = reason
        self._stop.set()

    def _on_message(self, msg: Any, rx_s: float) -> None:
        self.store.update(msg, rx_s)
        flight = self.flight
        if flight is not None:
            t = self.perf.now()
            self.flight_log.message(msg, rx_s)
            self.perf.add_inner("log", t)
            flight.on_message(msg, rx_s)

    def _pump(self, timeout_s: float) -> None:
        fd = self.link.fileno()
        if fd is not None and timeout_s > 0:
            select.select([fd], [], [], timeout_s)
        self.link.poll(self._on_message)
        self._link_events()

    def _request_streams(self) -> None:
        link = self.link
        for msg_id, hz in (
            (mavlink.MAVLINK_MSG_ID_ATTITUDE, 50.0),
            (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 50.0),
            (mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, 10.0),
            (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5.0),
        ):
            link.set_message_interval(msg_id, hz)
        if self.runtime.privileged:
            link.set_message_interval(mavlink.MAVLINK_MSG_ID_ODOMETRY, 50.0)

    def _link_events(self) -> None:
        for ev in self.link.pop_events():
            self.link_events.append(f"{ev.kind}: {ev.text}")
            print(f"visland companion: link {ev.kind}: {ev.text}", file=sys.stderr, flush=True)
            if ev.kind in ("discovered", "reconnected"):
                self._request_streams()
            if ev.kind == "restarted":
                self.store.reset_clock()
            if self.flight is not None:
                self.flight.on_link_event(ev.kind, ev.text)

    def _new_flight(self, index: int):
        from companion.record import CompanionLog

        stamp = time.strftime("%Y%m%d_%H%M%S")
        if self.cfg.log_dir:
            path = Path(self.cfg.log_dir) / f"companion_{stamp}_f{index:03d}.mcap"
            n = 1
            while path.exists():
                path = Path(self.cfg.log_dir) / f"companion_{stamp}_f{index:03d}_{n}.mcap"
                n += 1
        else:
            import tempfile

            path = Path(tempfile.mkdtemp(prefix="visland_companion_")) / f"f{index:03d}.mcap"
        meta = {
            "config": {"companion": self.cfg.to_dict()},
            "flight": {"index": index, "shadow": self.cfg.shadow, "mode": self.cfg.mode},
            "policy": {"name": self.runtime.name, "privileged": self.runtime.privileged},
        }
        flog = self.flight_log = CompanionLog(path, meta, self._clock)
        ctx = FlightContext(
            self.flight_cfg,
            self.link,
            self.store,
            self.camera.clock,
            self.safety,
            self._pump,
            self._clock,
            self.perf,
        )
        if self.tracker is not None:
            from companion.landing_target import LandingTargetController

            return LandingTargetController(ctx, self.tracker, flog, index)
        return FlightController(ctx, self.runtime, flog, index)

    def _close_flight(self) -> None:
        flight, flog = self.flight, self.flight_log
        if flight is None:
            return
        self.flight = self.flight_log = None
        summary = CompanionSummaryRecord(
            **flight.outcome.to_dict(),
            link=dataclasses.asdict(self.link.counters),
            clamped=self.safety.clamped,
            camera={  # what a lossy link did to the frames (UDP sources count these)
                k: getattr(self.camera, k)
                for k in ("bad_packets", "bad_size", "stale_frames")
                if hasattr(self.camera, k)
            },
            telemetry_rejected=dict(self.store.rejected),
        )
        out = summary.to_dict()
        flog.close(summary=summary)
        self.outcomes.append(out)
        print(
            f"visland companion: flight {flight.outcome.index} {flight.outcome.result}: "
            f"{flight.outcome.reason} ({flight.outcome.policy_commands} policy commands) "
            f"-> {flight.outcome.log_path}",
            file=sys.stderr,
            flush=True,
        )

    # ------------------------------------------------------------------ loop

    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        t0 = self._clock()
        index = 0
        perf = self.perf
        try:
            self.flight = self._new_flight(index)
            while not self._stop.is_set():
                t = perf.mark(self._in_air())
                if cfg.max_wall_s is not None and self._clock() - t0 > cfg.max_wall_s:
                    self.stop(f"max_wall_s = {cfg.max_wall_s} reached")
                    break
                fds = [fd for fd in (self.link.fileno(), self.camera.fileno()) if fd is not None]
                timeout = 0.01 if self.camera.fileno() is None else 0.02
                try:
                    select.select(fds, [], [], timeout)
                except InterruptedError:
                    pass
                t = perf.add("wait", t)
                self.link.poll(self._on_message)
                self._link_events()
                t = perf.add("mavlink", t)
                frames = self.camera.poll()
                t = perf.add("camera", t)
                flight = self.flight
                if frames and flight is not None:
                    for frame in frames[:-1]:  # answer the newest; older ones are logged only
                        self.flight_log.frame(frame)
                    flight.on_frame(frames[-1])
                    perf.add("other", t)  # frame sync, observation, safety: no part of PARTS
                if flight is not None:
                    flight.on_tick()
                    if flight.done:
                        self._close_flight()
                        index += 1
                        if cfg.flights and index >= cfg.flights:
                            break
                        self.flight = self._new_flight(index)
        finally:
            if self.flight is not None:
                self.flight.hand_back(cfg.on_exit, self._stop_reason or "exit")
                self._drain(0.3)
                self._close_flight()
            self.camera.close()
            self.link.close()
            perf.close()
        return {
            "flights": self.outcomes,
            "link_events": self.link_events,
            "link": dataclasses.asdict(self.link.counters),
            "camera": self.camera.counters() if hasattr(self.camera, "counters") else {},
            "stopped": self._stop_reason or None,
            "wall_s": self._clock() - t0,
            "perf": perf.report(),
        }

    def _in_air(self) -> bool:
        """A flight flies (OFFBOARD confirmed, or landed and waiting for the disarm): the
        window of :attr:`perf`."""
        flight = self.flight
        return flight is not None and flight.state in (FlightState.FLYING, FlightState.TOUCHDOWN)

    def _drain(self, seconds: float) -> None:
        """Keep the link alive briefly so the hand-back command is sent and acknowledged."""
        deadline = self._clock() + seconds
        while self._clock() < deadline and self.link.conn is not None:
            self._pump(0.02)


def run(cfg: CompanionConfig, policy: Any, policy_name: str) -> dict[str, Any]:
    """Run the companion until its flights are flown or SIGINT/SIGTERM; returns the report."""
    companion = Companion(cfg, policy, policy_name)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(
                sig, lambda s, _f: companion.stop(f"signal {signal.Signals(s).name}")
            )
    try:
        return companion.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def replay(path: Path, policy: Any, policy_name: str) -> dict[str, Any]:
    """Shadow replay of a recorded companion log (see :func:`companion.record.replay_log`)."""
    from companion.record import replay_log

    return replay_log(path, PolicyRuntime(policy, policy_name)).to_dict()


def run_from_args(
    args: argparse.Namespace,
    resolve_policy: Callable[[str, CompanionConfig], Any] | None = None,
    prog: str = "python -m companion",
) -> int:
    """Run (or ``--replay``) from parsed :func:`add_arguments` flags; prints the JSON report.
    ``resolve_policy(name, cfg)`` turns ``--policy`` into a policy object; the default loads a
    checkpoint (``tools/`` adds ``expert`` and ``cascade``)."""
    try:
        cfg = config_from_args(args)
        if not cfg.policy:
            raise CompanionError("--policy is required (a checkpoint path)")
        if resolve_policy is None:
            from companion.runtime import load_policy_file

            policy = load_policy_file(cfg.policy, cfg.torch_threads, cfg.runtime)
        else:
            policy = resolve_policy(cfg.policy, cfg)
        if args.replay is not None:
            report = replay(args.replay, policy, cfg.policy)
        else:
            report = run(cfg, policy, cfg.policy)
    except (ValueError, OSError, LinkError, CameraError) as exc:  # one clear line
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(report, indent=2, default=_json_default))
    if args.replay is not None:
        return 0 if not report["errors"] else 1
    failed = [f for f in report["flights"] if f["result"] == FlightResult.ENGAGE_FAILED]
    return 1 if failed else 0


def main(
    argv: list[str] | None = None,
    resolve_policy: Callable[[str, CompanionConfig], Any] | None = None,
    prog: str = "python -m companion",
) -> int:
    """``python -m companion`` (checkpoints only) and ``training.companion_process``."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr
    )
    return run_from_args(args, resolve_policy, prog)


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


if __name__ == "__main__":
    sys.exit(main())
