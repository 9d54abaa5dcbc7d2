"""The companion process: ``python -m companion`` / ``visland companion``.

One thread, one loop: ``select`` on the MAVLink port and the camera, feed the telemetry store,
answer each camera frame with one command (or, in shadow mode, only log it), run the timers of
the state machine (:mod:`companion.offboard`). One MCAP log per flight
(:mod:`companion.record`). SIGINT/SIGTERM hand control back (LAND or HOLD, ``on_exit``) and close
the log; the process then prints a JSON report on stdout. A flight that never began when the
companion stops (no armed autopilot seen, still waiting: e.g. the next one, opened after the last
landing of a simulator run) was never flown: its log is removed and the report says so under
``not_flown`` (the index, why it waited, why it stopped), instead of a log and a flight marked
aborted (:attr:`~companion.flight.FlightMachine.began`).

Configuration: :class:`~companion.config.CompanionConfig` (:mod:`companion.config`) — the
hardware template's defaults, then a TOML file (``--config``, table ``[companion]``; without it
the template installed with the package), then command-line flags.
``--replay LOG`` runs a recorded log through the policy instead (shadow, no link) and reports
how far the recomputed commands are from the recorded ones; ``--check`` runs the bench check
(:mod:`companion.check`: camera, detection, link, parameters; nothing sent).
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import json
import logging
import select
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.camera import CameraError
from companion.config import (
    CompanionConfig,
    CompanionError,
    add_arguments,
    config_from_args,
    open_camera_and_link,
)
from companion.contract.companion_records import CompanionSummaryRecord
from companion.contract.perf import LoopPerf, pin_to_cpus
from companion.contract.records import EventKind
from companion.flight import FlightContext
from companion.link import LinkError, mavlink
from companion.offboard import FlightController
from companion.runtime import PolicyRuntime
from companion.safety import SafetyMonitor
from companion.states import FailsafeReason, FlightResult, FlightState
from companion.telemetry import TelemetryStore

__all__ = [
    "main",
    "run",
    "run_from_args",
]

log = logging.getLogger("visland.companion")


def _left_to_the_pilot(flight) -> bool:
    """The flight ended ``pad_not_found``, the vehicle still in the air and the pilot's (left
    in hold, or in the offboard-loss action's mode): the next flight waits for a disarm
    (``FlightMachine.await_disarm``) instead of taking it back. (A plain ``handed_back`` does
    not: the SITL's next episode begins as a switch to HOLD.)"""
    failsafe = flight.outcome.failsafe
    return (
        flight.outcome.result is FlightResult.FAILSAFE
        and failsafe is not None
        and failsafe.reason is FailsafeReason.PAD_NOT_FOUND
    )


# --------------------------------------------------------------------------- the process


class Companion:
    """The process: build from a config and a policy, then :meth:`run`; :meth:`stop` from a
    signal handler or another thread."""

    def __init__(self, cfg: CompanionConfig, policy: Any, policy_name: str) -> None:
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
        self.log_scene = _log_scene(cfg.log_scene)
        self.store = TelemetryStore()
        self.camera, self.link = open_camera_and_link(cfg)
        if hasattr(self.camera, "follow"):  # camera_roi: cut each frame where the policy looks
            self.camera.follow(self.tracker if self.tracker is not None else self.runtime)
        self._stop = threading.Event()
        self._stop_reason = ""
        self._heard_autopilot = False
        """The autopilot's first HEARTBEAT has been heard (:meth:`_first_heartbeat`)."""
        self.flight = None
        self.flight_log = None
        self.outcomes: list[dict[str, Any]] = []
        self.not_flown: dict[str, Any] | None = None
        """The flight that was waiting when the companion stopped (its log removed)."""
        self.link_events: list[str] = []
        self._clock: Callable[[], float] = time.monotonic
        self._requested_streams = False
        self.perf = LoopPerf()
        """Wall time per part of the loop while a flight is in the air (the report's
        ``perf``)."""
        self._wall_offset: float | None = None
        self.live = None
        if cfg.live:
            from companion.live import LiveView, parse_live

            host, port = parse_live(cfg.live)
            self.live = LiveView(host, port, name="visland companion")
            print(f"visland companion: live view on ws://{host}:{self.live.port}", file=sys.stderr)

    # ------------------------------------------------------------------ plumbing

    def stop(self, reason: str = "stopped") -> None:
        self._stop_reason = reason
        self._stop.set()

    def _on_message(self, msg: Any, rx_s: float) -> None:
        self.store.update(msg, rx_s)
        if not self._heard_autopilot and msg.get_type() == "HEARTBEAT":
            self._first_heartbeat(msg)
        flight = self.flight
        if flight is not None:
            t = self.perf.now()
            flight_log = self.flight_log
            # queued (receipt order and stamps kept): written when the loop is about to idle,
            # or after a frame's answer; never between a frame and its answer
            flight_log.deferring = True
            flight_log.message(msg, rx_s)
            self.perf.add_inner("log", t)
            flight.on_message(msg, rx_s)

    def _first_heartbeat(self, msg: Any) -> None:
        """The autopilot's first HEARTBEAT this process hears: a vehicle already armed (a
        companion restarted in the air, after a failsafe handed it to the pilot or the
        autopilot) is not taken — the flight waits for a disarm — unless ``engage_in_air``."""
        if msg.get_srcComponent() != self.link.target_component:
            return
        self._heard_autopilot = True
        hb = self.store.heartbeat
        if hb is None or not hb.armed or self.cfg.engage_in_air or self.cfg.shadow:
            return
        why = "the vehicle was armed when the companion started (restarted in the air?)"
        log.warning("%s: not taking control; the pilot lands it (--engage-in-air takes it)", why)
        self.link.send_statustext(4, "visland: armed at start, not taking control")
        if self.flight is not None:
            self.flight.await_disarm = why
            self.flight.began = True  # armed: its log says why it waits

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
        if self.runtime.privileged or self.live is not None:  # live: the truth beside the estimate
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
        scene = None
        if self.log_scene:
            from companion.live.scene_log import SceneStream

            scene = SceneStream()
        flog = self.flight_log = CompanionLog(path, meta, self._clock, self._log_failed, scene)
        ctx = FlightContext(
            self.flight_cfg,
            self.link,
            self.store,
            self.camera.clock,
            self.safety,
            self._pump,
            self._clock,
            self.perf,
            self.live,
        )
        if self.tracker is not None:
            from companion.landing_target import LandingTargetController

            return LandingTargetController(ctx, self.tracker, flog, index)
        return FlightController(ctx, self.runtime, flog, index)

    def _watch_wall_clock(self) -> None:
        """Note a step of the wall clock (NTP syncing on a board that booted without a clock,
        a pilot setting the date): control and staleness run on the monotonic clock and the
        log's times on the epoch taken when it was opened plus monotonic seconds, so a step
        changes neither — it is said, in the flight's events and on stderr."""
        offset = time.time() - self._clock()
        if self._wall_offset is None:
            self._wall_offset = offset
            return
        step = offset - self._wall_offset
        if abs(step) < WALL_STEP_S:
            return
        self._wall_offset = offset
        text = f"wall clock stepped by {step:+.1f} s (control and log times unaffected)"
        print(f"visland companion: {text}", file=sys.stderr, flush=True)
        self.link_events.append(f"clock_step: {text}")
        if self.flight is not None:
            self.flight.note(EventKind.CLOCK_STEP, text)

    def _log_failed(self, text: str) -> None:
        """The flight log stopped (a full card): fly on, and say so — on stderr, in the flight's
        events and to the pilot as a STATUSTEXT (WARNING)."""
        print(
            f"visland companion: {text}; the flight goes on unlogged", file=sys.stderr, flush=True
        )
        self.link_events.append(f"log_stopped: {text}")
        if self.flight is not None:
            self.flight.outcome.events.append(f"log_stopped: {text}")
        self.link.send_statustext(4, "visland: flight log stopped (disk full?)")

    def _drop_unflown(self, reason: str) -> None:
        """Stop the flight that never began (still WAITING): remove its log and note it in
        :attr:`not_flown`."""
        flight, flog = self.flight, self.flight_log
        self.flight = self.flight_log = None
        waiting = flight.outcome.events[-1] if flight.outcome.events else "waiting"
        flog.close()
        Path(flog.path).unlink(missing_ok=True)
        self.not_flown = {"index": flight.outcome.index, "waiting": waiting, "stopped": reason}
        print(
            f"visland companion: flight {flight.outcome.index} not flown ({waiting}; {reason}):"
            " its log removed",
            file=sys.stderr,
            flush=True,
        )

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
        release_free_memory()
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
                self._watch_wall_clock()
                if cfg.max_wall_s is not None and self._clock() - t0 > cfg.max_wall_s:
                    self.stop(f"max_wall_s = {cfg.max_wall_s} reached")
                    break
                if self.flight_log is not None:
                    self.flight_log.flush_pending()  # before idling: what the last pass queued
                    t = perf.add("log", t)
                fds = [fd for fd in (self.link.fileno(), self.camera.fileno()) if fd is not None]
                timeout = 0.01 if self.camera.fileno() is None else 0.02
                select.select(fds, [], [], timeout)  # EINTR is retried (PEP 475)
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
                        hb = self.store.heartbeat
                        if _left_to_the_pilot(flight) and hb is not None and hb.armed:
                            self.flight.await_disarm = (
                                f"the last flight ended in the air ({flight.outcome.result})"
                            )
                            self.flight.began = True  # armed: its log says why it waits
        finally:
            if self.flight is not None and not self.flight.began:
                self._drop_unflown(self._stop_reason or "exit")
            if self.flight is not None:
                self.flight.hand_back(cfg.on_exit, self._stop_reason or "exit")
                self._drain(0.3)
                self._close_flight()
            self.camera.close()
            self.link.close()
            perf.close()
            if self.live is not None:
                self.live.close()
        return {
            "flights": self.outcomes,
            "not_flown": self.not_flown,
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


def release_free_memory() -> None:
    """Hand the C heap's free pages back to the OS between flights (glibc ``malloc_trim``; a
    no-op elsewhere). Without it a companion's resident memory crept up ~45 kB a flight with no
    Python object left behind (``visland soak``: +8.9 MB over 180 flights, flat with it): each
    flight's log buffers and solver arrays are freed into a heap that fragments, not returned."""
    global _LIBC
    if _LIBC is None:
        try:
            _LIBC = ctypes.CDLL("libc.so.6")
            _LIBC.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):
            _LIBC = False
    if _LIBC:
        _LIBC.malloc_trim(0)


_LIBC: Any = None
WALL_STEP_S = 1.0
"""A change of the wall clock against the monotonic one by this much is a step (drift is ppm)."""


def run(cfg: CompanionConfig, policy: Any, policy_name: str) -> dict[str, Any]:
    """Run the companion until its flights are flown or SIGINT/SIGTERM; returns the report."""
    companion = Companion(cfg, policy, policy_name)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(
                sig, lambda s, _f: companion.stop(f"signal {signal.Signals(s).name}")
            )
        if hasattr(signal, "SIGXFSZ"):  # a file-size limit fails the write (EFBIG), not the flight
            previous[signal.SIGXFSZ] = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
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
        pin_to_cpus("companion")  # VISLAND_COMPANION_CPUS
        if resolve_policy is None:
            from companion.runtime import load_policy_file

            policy = load_policy_file(cfg.policy, cfg.torch_threads, cfg.runtime)
        else:
            policy = resolve_policy(cfg.policy, cfg)
        policy = cfg.with_estimator(policy)
        if args.replay is not None:
            report = replay(args.replay, policy, cfg.policy)
        elif getattr(args, "check", False):
            from companion.check import run_check

            report = run_check(cfg, policy, cfg.policy, sys.stdout)
        else:
            report = run(cfg, policy, cfg.policy)
    except (ValueError, OSError, LinkError, CameraError) as exc:  # one clear line
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if getattr(args, "check", False):
        return 0 if report["ok"] else 1  # its lines were printed as it went
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


def _log_scene(setting: str) -> bool:
    """Whether flight logs take the live view's picture (``log_scene``): 'auto' where
    foxglove-sdk is installed (a line on stderr where not)."""
    if setting == "off":
        return False
    try:
        import foxglove.messages  # noqa: F401
    except ImportError:
        if setting == "on":
            raise CompanionError(
                "log_scene = 'on' needs foxglove-sdk: pip install 'visland[live]' (or 'auto')"
            ) from None
        print(
            "visland companion: flight logs without the live view's picture (foxglove-sdk not "
            "installed; visland log scene adds it later)",
            file=sys.stderr,
        )
        return False
    return True
