"""``visland companion --check``: the bench check, on the ground with the props off.

It opens the configured camera and autopilot link, then prints, once a second until Ctrl-C or
``max_wall_s``: the camera's frame rate, the policy's pad detection and bearing on the newest
frame (the CNN and pad estimator, :class:`~companion.landing_target.PadTracker`), the radar
range and attitude, and the telemetry rates; it prints the link's events, the autopilot's mode
and arming as they change, and the parameters the companion reads (hover thrust; ArduPilot's
GUID_OPTIONS). It never sends a setpoint or a mode change: only its HEARTBEAT,
SET_MESSAGE_INTERVAL (the telemetry rates it asks for) and PARAM_REQUEST_READ. After a few
seconds without an autopilot or without frames it prints what to check (docs/deploy.md,
"Troubleshooting").
"""

from __future__ import annotations

import math
import select
import signal
import threading
import time
from collections import Counter
from typing import Any, TextIO

from companion.config import CompanionConfig, open_camera_and_link
from companion.landing_target import LandingTargetError, PadTracker, landing_target_fields
from companion.link import mavlink
from companion.telemetry import TelemetryStore, assemble_observation

__all__ = ["run_check"]

_PRINT_PERIOD_S = 1.0
_HINT_AFTER_S = 5.0
_STREAMS = (
    (mavlink.MAVLINK_MSG_ID_ATTITUDE, 50.0),
    (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 50.0),
    (mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, 10.0),
)
"""The telemetry the policy reads, at the rates the companion asks for in flight."""
_TELEMETRY = ("ATTITUDE", "HIGHRES_IMU", "DISTANCE_SENSOR")


def _no_autopilot_hint(cfg: CompanionConfig) -> str:
    serial = cfg.connect.startswith(("serial:", "/dev/"))
    where = "the serial port" if serial else "the link"
    text = (
        f"no HEARTBEAT from an autopilot on {cfg.connect} after {_HINT_AFTER_S:g} s: check "
        f"{where}'s wiring (TX to RX), the baud rate and the autopilot's MAVLink instance "
        "(PX4 MAV_1_CONFIG = TELEM 2, SER_TEL2_BAUD; ArduPilot SERIAL2_PROTOCOL = 2)"
    )
    if "ttyAMA0" in cfg.connect:
        text += (
            "; on a Raspberry Pi 4 /dev/ttyAMA0 is the Bluetooth UART unless "
            "dtoverlay=disable-bt is in /boot/firmware/config.txt (visland companion "
            "install-service --board pi4 writes it; reboot after)"
        )
    return text


class _BenchCheck:
    """The check's state: what it has seen so far, and the lines it prints."""

    def __init__(self, cfg: CompanionConfig, policy: Any, policy_name: str, out: TextIO) -> None:
        self.cfg, self.out, self.policy_name = cfg, out, policy_name
        try:
            self.tracker: PadTracker | None = PadTracker(policy, cfg.target_timeout_s)
        except LandingTargetError:
            self.tracker = None  # a privileged policy has no camera: link and camera only
        self.store = TelemetryStore()
        self.camera, self.link = open_camera_and_link(cfg)
        if self.tracker is not None and hasattr(self.camera, "follow"):  # camera_roi
            self.camera.follow(self.tracker)
        self.stop = threading.Event()
        self.frames = 0
        self.pad_seen = 0
        self.received: Counter[str] = Counter()
        self.window: Counter[str] = Counter()
        self.params: dict[str, float] = {}
        self.heartbeat: tuple[str, bool] | None = None
        self.discovered = False
        self.last_track = ""

    def say(self, text: str) -> None:
        print(text, file=self.out, flush=True)

    def on_message(self, msg: Any, rx_s: float) -> None:
        self.store.update(msg, rx_s)
        name = msg.get_type()
        self.received[name] += 1
        self.window[name] += 1
        hb = self.store.heartbeat
        if name == "HEARTBEAT" and hb is not None:
            state = (self.link.profile.mode_name(hb.custom_mode), hb.armed)
            if state != self.heartbeat:
                self.heartbeat = state
                self.say(f"autopilot: mode {state[0]}, {'armed' if state[1] else 'disarmed'}")

    def on_link_events(self) -> None:
        profile = self.link.profile
        for ev in self.link.pop_events():
            self.say(f"link {ev.kind}: {ev.text}")
            if ev.kind in ("discovered", "reconnected"):
                self.discovered = True
                for msg_id, hz in _STREAMS:
                    self.link.set_message_interval(msg_id, hz)
                for name in filter(None, (profile.hover_param, profile.thrust_param)):
                    self.link.request_param(name)
        for name in filter(None, (profile.hover_param, profile.thrust_param)):
            value = self.link.param(name)
            if value is not None and name not in self.params:
                self.params[name] = value
                self.say(f"param {name} = {value:g}")

    def on_frame(self, frame: Any) -> None:
        store = self.store
        if self.tracker is None:
            self.last_track = "no pad detection (privileged policy: no camera)"
            return
        if store.attitude is None or store.imu is None or store.range is None:
            self.last_track = "no pad detection yet (waiting for ATTITUDE, HIGHRES_IMU, range)"
            return
        at = frame.time_s if self.camera.clock == "autopilot" else None
        obs = assemble_observation(frame, store, self.link.param(self.link.profile.hover_param), at)
        track = self.tracker.step(obs)
        if track.error is not None:
            self.last_track = f"policy error: {track.error}"
            return
        self.pad_seen += track.seen
        seen = f"pad {'seen' if track.seen else 'not seen'} (p = {track.visibility:.2f})"
        fields = None
        if track.target_rel_ned_m is not None:
            fields = landing_target_fields(track.target_rel_ned_m, obs.attitude_rad)
        if fields is None:
            self.last_track = seen + ", no bearing yet"
        else:
            self.last_track = (
                f"{seen}, bearing {math.degrees(fields.angle_x_rad):+.1f} deg right "
                f"{-math.degrees(fields.angle_y_rad):+.1f} deg forward, {fields.distance_m:.1f} m"
            )

    def status_line(self, t_s: float, period_s: float) -> str:
        rng, att = self.store.range, self.store.attitude
        radar = "range none" if rng is None else f"range {rng.range_m:.2f} m"
        attitude = ""
        if att is not None:
            roll, pitch, _ = (math.degrees(a) for a in att.attitude_rad)
            attitude = f"  roll {roll:+.1f} pitch {pitch:+.1f} deg"
        rates = "  ".join(f"{n} {self.window[n] / period_s:.0f} Hz" for n in _TELEMETRY)
        fps = self.window["frame"] / period_s
        return (
            f"t {t_s:5.1f} s  camera {fps:.1f} fps  {self.last_track or 'no frame yet'}  |  "
            f"{radar}{attitude}  |  {rates}"
        )

    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        self.say(
            f"visland companion --check: camera {cfg.camera}, link {cfg.connect} "
            f"({cfg.autopilot}), policy {self.policy_name}; sends no setpoint and no mode change"
        )
        t0 = last_print = time.monotonic()
        hinted: set[str] = set()
        try:
            while not self.stop.is_set():
                now = time.monotonic()
                if cfg.max_wall_s is not None and now - t0 > cfg.max_wall_s:
                    break
                fds = [f for f in (self.link.fileno(), self.camera.fileno()) if f is not None]
                select.select(fds, [], [], 0.02)  # EINTR is retried (PEP 475)
                self.link.poll(self.on_message)
                self.on_link_events()
                frames = self.camera.poll()
                if frames:
                    self.window["frame"] += len(frames)
                    self.frames += len(frames)
                    self.on_frame(frames[-1])  # the newest: what the policy would answer
                if now - last_print >= _PRINT_PERIOD_S:
                    self.say(self.status_line(now - t0, now - last_print))
                    self.window.clear()
                    last_print = now
                if now - t0 > _HINT_AFTER_S:
                    if not self.discovered and "link" not in hinted:
                        hinted.add("link")
                        self.say("hint: " + _no_autopilot_hint(cfg))
                    if not self.frames and "camera" not in hinted:
                        hinted.add("camera")
                        self.say(
                            f"hint: no frame from {cfg.camera} after {_HINT_AFTER_S:g} s: check "
                            "the device (v4l2-ctl --list-devices), the user's 'video' group and "
                            "the pipeline (docs/deploy.md, section 5)"
                        )
        finally:
            self.camera.close()
            self.link.close()
        return self.report()

    def report(self) -> dict[str, Any]:
        counters = self.link.counters
        telemetry_ok = all(self.received[n] for n in _TELEMETRY)
        ok = self.discovered and self.frames > 0 and telemetry_ok
        self.say(
            f"check {'passed' if ok else 'FAILED'}: {self.frames} frames ({self.pad_seen} with "
            f"the pad seen), autopilot {'discovered' if self.discovered else 'not discovered'}, "
            f"telemetry {dict((n, self.received[n]) for n in _TELEMETRY)}, params {self.params}; "
            f"setpoints sent {counters.tx_setpoints}, commands sent {counters.tx_commands} "
            "(SET_MESSAGE_INTERVAL, PARAM_REQUEST_READ only)"
        )
        return {
            "ok": ok,
            "frames": self.frames,
            "pad_seen": self.pad_seen,
            "autopilot_discovered": self.discovered,
            "telemetry": {n: self.received[n] for n in _TELEMETRY},
            "params": dict(self.params),
            "tx_setpoints": counters.tx_setpoints,
        }


def run_check(cfg: CompanionConfig, policy: Any, policy_name: str, out: TextIO) -> dict[str, Any]:
    """Run the bench check until SIGINT/SIGTERM or ``cfg.max_wall_s``; its lines go to
    ``out``. Returns its summary (``ok``: autopilot discovered, frames and telemetry seen).

    Raises:
        companion.camera.CameraError, companion.link.LinkError: cannot open the camera or link.
    """
    check = _BenchCheck(cfg, policy, policy_name, out)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda _s, _f: check.stop.set())
    try:
        return check.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
