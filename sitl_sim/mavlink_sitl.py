"""``visland sitl``: the simulator behind a PX4-like MAVLink 2 autopilot endpoint over real UDP.

One process, one thread, one clock. The loop advances the SITL clock one physics step (4 ms at
250 Hz) at a time; everything the outside world sees is stamped with that sim clock
(``time_boot_ms``/``time_usec`` = time since SITL start, monotonic across episodes; TIMESYNC
answers in sim ns). Per physics step:

1. physics (:class:`~sitl_sim.simulator.Simulator`) with the autopilot's command — or nothing
   while the vehicle is frozen (HOLD: before the take-over, and whenever HOLD is selected);
2. every stream whose interval is due (ATTITUDE, HIGHRES_IMU, ... at SET_MESSAGE_INTERVAL rates);
3. at each control period (10 Hz): offboard/land checks, episode end, the camera frame (UDP
   packet of :mod:`companion.camera_packet`, stamped with its exposure time; not sent when the
   scenario's ``[sensors]`` loses it), the ground-truth log record; in lockstep and OFFBOARD,
   then wait for the companion's answer to a frame that was sent.

The flight log is a training record: for each control step the companion flies (in flight,
before touchdown, armed in OFFBOARD) it also holds ``/observation`` (the attitude, IMU and range
readings last streamed) and ``/command`` (the setpoint flown for the period after the frame),
keyed by frame id like the in-process log, so ``visland relabel`` labels SITL flights (DAgger
rollouts through the real processes).

**Lockstep** (default): in OFFBOARD the clock stops after each camera frame until a
SET_ATTITUDE_TARGET arrives that was received after the frame was sent and is stamped
(``time_boot_ms``) at or after the frame's time (``lockstep_require_stamp``; turn it off for
clients that stamp with their own clock, e.g. MAVSDK), or until ``lockstep_timeout_s`` of wall
time passes (counted; the last setpoint holds, so a dead client meets COM_OF_LOSS_T after 10
frames). Outside OFFBOARD nobody paces the loop: LAND and the wait for disarm run as fast as the
machine allows, and the frozen HOLD phase runs at wall-clock speed (the companion's hand-shake
happens in wall time). **Real time** (``lockstep=False``): the clock follows the wall clock ×
``speed`` throughout; the last setpoint holds between messages.

**Episodes**: episode ``i`` starts at ``InitialStateSampler(scenario, seed).sample(i)`` in HOLD,
armed, frozen; the flight starts at the first control period after the vehicle is armed in a mode
other than HOLD (the simulator is re-seeded then, and the episode's world is drawn again as
``episode_world(scenario, seed, i)``, so a flight does not depend on how long HOLD
lasted); it ends at touchdown + disarm (auto after COM_DISARM_LAND), at ``episode_timeout_s`` of
flight, or after ``hold_timeout_s`` without a take-over. One MCAP flight log per episode;
``first_episode`` lets parallel SITLs fly disjoint parts of one seed. With a ``[vehicle]``
scenario section each episode flies its own airframe, and the autopilot is tuned for it as a
tuned PX4 is: ``MPC_THR_HOVER`` is that airframe's hover thrust (a change is announced with a
PARAM_VALUE at the episode start) and AUTO.LAND flies it.

This module wires the parts and runs the loop; the rest lives one job per module:

* :mod:`sitl_sim.sitl_config`: :class:`SitlConfig` and its ``--flags``;
* :mod:`sitl_sim.sitl_clock`: the sim clock, the lockstep frame wait, real-time pacing;
* :mod:`sitl_sim.sitl_episode`: episode lifecycle and the flight log;
* :mod:`sitl_sim.mavlink_messages`: message builders and streams (``PUBLISHES``);
* :mod:`sitl_sim.mavlink_handlers`: ``handle_<message>`` and command handlers (``SUBSCRIBES``,
  ``COMMANDS``);
* :mod:`sitl_sim.params`: the parameter table;
* :mod:`sitl_sim.link_impairment`: the scenario's ``[link]`` (real time only): the offboard
  link's datagrams both ways and the camera's pass through it; due ones are released at the top
  of every loop pass, and the loop never sleeps past the next release.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import select
import signal
import socket
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.contract import Command, GroundTruth
from companion.contract.camera_packet import encode_frame
from companion.contract.signing import signing_key_bytes
from sitl_sim.airframe import check_airframe_can_hover
from sitl_sim.ardupilot import ardupilot_params, new_autopilot
from sitl_sim.autopilot import AutopilotParams, FlightMode, LandController
from sitl_sim.config import SimConfig, VehicleConfig, load_sim, load_vehicle
from sitl_sim.errors import ConfigError, SimError
from sitl_sim.land_controller import CascadeLandController
from sitl_sim.link_impairment import LinkConfig, LinkImpairment
from sitl_sim.mavlink_endpoint import LinkStats, MavlinkEndpoint, SitlError
from sitl_sim.mavlink_handlers import MessageHandlers
from sitl_sim.mavlink_messages import MessageBuilders
from sitl_sim.metrics import EpisodeResult, summarize
from sitl_sim.params import parse_param_overrides, with_param
from sitl_sim.scenario import InitialStateSampler, Scenario, load_scenario
from sitl_sim.simulator import Simulator
from sitl_sim.sitl_clock import FrameWait, Pacer, SimClock
from sitl_sim.sitl_config import (
    SitlConfig,
    add_sitl_arguments,
    sitl_config_from_args,
)
from sitl_sim.sitl_episode import Episode, EpisodeLifecycle
from sitl_sim.sitl_precland import PreclandLoop

__all__ = ["MavlinkSitl", "main", "run_sitl"]

log = logging.getLogger("visland.sitl")

_ON_GROUND_DOWN_M = -0.01  # within 1 cm of the ground plane counts as on the ground


class MavlinkSitl(MessageBuilders, MessageHandlers, EpisodeLifecycle, PreclandLoop):
    """The MAVLink SITL: build it (binds the ports), then :meth:`run` (blocking) or
    :meth:`stop` from another thread. Use as a context manager to release the ports.

    Args:
        config: the SitlConfig.
        land_controller_factory: builds the AUTO.LAND controller from (vehicle, planet), called
            again at an episode start whose vehicle differs (a scenario's ``[vehicle]``); the
            default is the privileged
            :class:`~sitl_sim.land_controller.CascadeLandController` (ground truth in).

    Raises:
        SitlPortInUseError: the MAVLink port is taken.
        ConfigError: a TOML file is missing or invalid.
    """

    def __init__(
        self,
        config: SitlConfig,
        land_controller_factory: Callable[[VehicleConfig, Any], LandController] | None = None,
    ) -> None:
        self.config = config
        self.vehicle = load_vehicle(config.vehicle_config)
        self.scenario: Scenario = load_scenario(config.scenario)
        sim_cfg: SimConfig = load_sim(config.sim_config).with_planet(self.scenario.world)
        if config.noiseless:
            sim_cfg = sim_cfg.noiseless()
        self.sim_cfg = sim_cfg
        self.episode_timeout_s = config.episode_timeout_s or sim_cfg.episode_timeout_s
        self.clock = SimClock(sim_cfg.physics_rate_hz, sim_cfg.physics_dt_s)
        self._substeps = sim_cfg.substeps
        if self.scenario.vehicle is not None:
            check_airframe_can_hover(self.scenario.vehicle, self.vehicle, sim_cfg.planet)
        self._land_controller_factory = land_controller_factory or _default_land_controller
        self.land_controller = self._land_controller_factory(self.vehicle, sim_cfg.planet)
        self._land_controller_vehicle = self.vehicle
        self.params = _initial_params(config, self.vehicle.hover_thrust_norm(sim_cfg.planet))
        self.autopilot = new_autopilot(config.autopilot, self.params, armed=config.start_armed)
        self._offboard_paced = True
        """In lockstep, OFFBOARD frames wait for the client's answer (False after an unanswered
        frame, for an autopilot that ``runs_free_when_unanswered``, until it answers again)."""
        self.sampler = InitialStateSampler(self.scenario, config.seed)
        self.link_impairment = _link_impairment(self.scenario, config)
        """The impaired offboard + camera link (None: a perfect link)."""
        self.results: list[EpisodeResult] = []
        self.lockstep_timeouts = 0
        self._pacer = Pacer(self.clock.dt_s, config.speed)
        self.ignored_messages: Counter[str] = Counter()
        key = signing_key_bytes(config.signing_key) if config.signing_key else None
        self.sim = Simulator(self.vehicle, sim_cfg, render=config.render)
        try:
            self.endpoint = MavlinkEndpoint(
                (config.host, config.mavlink_port),
                (config.remote_host, config.remote_port),
                signing_key=key,
            )
        except SitlError:
            self.sim.close()  # the pybullet client must not outlive a failed start
            raise
        self.gcs_endpoint: MavlinkEndpoint | None = None
        """The ground-station link (None: ``gcs`` off, or its port was taken)."""
        if config.gcs:
            try:
                self.gcs_endpoint = MavlinkEndpoint(
                    (config.host, config.gcs_port),
                    (config.gcs_remote_host, config.gcs_remote_port),
                    signing_key=key,
                    name="gcs",
                )
            except SitlError as exc:
                # The offboard link is the one a flight needs; a second SITL (or a PX4) holding
                # 18570 must not stop this one. Said once, loudly; --gcs-port / --no-gcs fix it.
                log.warning("ground-station link off: %s (use --gcs-port or --no-gcs)", exc)
        self.endpoint.set_impairment(self.link_impairment)
        self._endpoints = [self.endpoint] + (
            [self.gcs_endpoint] if self.gcs_endpoint is not None else []
        )
        self._rx_endpoint = self.endpoint
        self._camera_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._camera_addr = (config.camera_host, config.camera_port)
        self.camera_tx_errors = 0
        self.camera_frames_dropped = 0
        """Frames the scenario's ``frame_drop_prob`` lost (not sent)."""
        self._init_dispatch()
        self._init_streams()
        self._init_precland()
        self._stop = threading.Event()
        self._frame_id = 0
        self._flying = False
        self._land_cmd: Command | None = None
        self._land_point_ne: np.ndarray | None = None
        """AUTO.LAND's landing point (north, east, pad frame): where the mode was engaged."""
        self._wait: FrameWait | None = None
        self._episode: Episode | None = None
        self._done = False
        self._closed = False
        self._last_stats_log_wall = 0.0
        self._last_errors_logged = 0

    # ------------------------------------------------------------------ public

    @property
    def time_s(self) -> float:
        """The SITL clock: sim seconds since start (MAVLink time_boot_ms / 1000)."""
        return self.clock.time_s

    @property
    def time_us(self) -> int:
        return self.clock.time_us

    @property
    def pacing_overruns(self) -> int:
        """Times the paced clock fell behind the wall clock and re-anchored."""
        return self._pacer.overruns

    @property
    def stats(self) -> LinkStats:
        """The offboard link's counters (read-only from other threads)."""
        return self.endpoint.stats

    @property
    def gcs_stats(self) -> LinkStats | None:
        """The ground-station link's counters (None without that link)."""
        return self.gcs_endpoint.stats if self.gcs_endpoint is not None else None

    def stop(self) -> None:
        """Ask :meth:`run` to return (thread-safe); the current episode is logged as aborted."""
        self._stop.set()

    def run(self) -> list[EpisodeResult]:
        """Fly ``config.episodes`` episodes (or until :meth:`stop`); returns their results."""
        cfg = self.config
        wall0 = time.monotonic()
        try:
            self._start_episode(cfg.first_episode)
            while not self._stop.is_set() and not self._done:
                now = time.monotonic()
                if cfg.max_wall_s is not None and now - wall0 > cfg.max_wall_s:
                    log.warning("max_wall_s = %.1f s reached: stopping", cfg.max_wall_s)
                    break
                self._release_link()
                self._poll()
                wait = self._wait
                if wait is not None:
                    if wait.pending(now):
                        self._sleep(min(wait.deadline_wall_s - now, 0.05))
                        continue
                    if not wait.answered:
                        self.lockstep_timeouts += 1
                        self._precland_wait_timed_out()
                        if self.autopilot.runs_free_when_unanswered:
                            self._offboard_paced = False
                    self._wait = None
                # Nobody paces HOLD or real time: the wall clock does (lockstep flight runs free).
                paced = not self._physics_running() or not cfg.lockstep
                delay = self._pacer.delay_s(now, self.clock.tick, paced)
                if delay > 0:
                    self._sleep(min(delay, 0.05))
                    continue
                self._tick_once()
        finally:
            self._finish_episode(aborted=not self._done)
            self._drain_link()
            self.close()
        return list(self.results)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for endpoint in self._endpoints:
            endpoint.close()
        self._camera_sock.close()
        self.sim.close()

    def __enter__(self) -> MavlinkSitl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ loop pieces

    def _physics_running(self) -> bool:
        return self._flying and self.autopilot.physics_running

    def _sleep(self, timeout_s: float) -> None:
        """Wait for a datagram (on any link), the timeout, or the impaired link's next
        release."""
        imp = self.link_impairment
        if imp is not None:
            due = imp.next_release_s()
            if due is not None:
                timeout_s = min(timeout_s, due - time.monotonic())
        if timeout_s > 0:
            select.select([e.fileno() for e in self._endpoints], [], [], timeout_s)

    def _poll(self) -> None:
        for endpoint in self._endpoints:
            self._rx_endpoint = endpoint  # whose counters the handlers' rejections go to
            accepted, errors = endpoint.receive()
            for err in errors:
                self._log_rx_error(err, endpoint.name)
            for inbound in accepted:
                self._log_inbound(inbound)
                name = inbound.msg.get_type()
                handler = self._handlers.get(name)
                if handler is None:
                    self.ignored_messages[name] += 1
                    continue
                handler(inbound.msg, inbound)
        self._rx_endpoint = self.endpoint
        self._announce_events()
        self._maybe_log_stats()

    def _release_link(self) -> None:
        """Send what the impaired link releases now (MAVLink and camera; received datagrams
        are released in :meth:`_poll`)."""
        imp = self.link_impairment
        if imp is None:
            return
        self.endpoint.release()
        for datagram in imp.streams["camera_tx"].due(imp.clock()):
            self._camera_sendto(datagram)

    def _drain_link(self) -> None:
        """Before closing: let the impaired link deliver what it still holds for the companion
        (the disarm HEARTBEAT of the last touchdown), as a real link would after we stop."""
        imp = self.link_impairment
        if imp is None:
            return
        cfg = imp.config
        deadline = time.monotonic() + 1e-3 * (cfg.delay_ms + cfg.jitter_ms) + 0.01
        held = (imp.streams["mavlink_tx"], imp.streams["camera_tx"])
        while any(s.held for s in held) and (now := time.monotonic()) < deadline:
            due = min(t for s in held if (t := s.next_release_s()) is not None)
            time.sleep(min(max(due - now, 0.0), 0.01))
            self._release_link()

    def _update_link_cut(self) -> None:
        """The ``outage_s`` window, on flight time: log its start and end."""
        imp = self.link_impairment
        if imp is None:
            return
        cut = imp.config.in_outage(self.sim.time_s if self._flying else None)
        if cut != imp.cut:
            imp.cut = cut
            what = "cut" if cut else "restored"
            self._event("link_outage", f"link {what} at flight time {self.sim.time_s:.3f} s")
            log.info("link %s at flight time %.3f s (outage_s)", what, self.sim.time_s)

    def _tick_once(self) -> None:
        running = self._physics_running()
        if running:
            cmd = self._current_command()
            if self.clock.phase % self._substeps == 0:
                self._log_commands(cmd)
            self.sim.step_physics(cmd)
        self._update_link_cut()
        self.clock.tick += 1
        boundary = self.clock.phase % self._substeps == 0
        if boundary and not self._control_period():
            return  # the episode ended here; the next one starts at the next tick
        self._emit_streams()
        if running:
            self._precland_tick()  # after the streams: it reads the readings they sent
        if boundary:
            stamp_us = self._send_frame()
            ap = self.autopilot
            if (
                stamp_us is not None  # a lost frame has no answer to wait for
                and self.config.lockstep
                and self._physics_running()
                and (
                    (ap.mode is FlightMode.OFFBOARD and self._offboard_paced)
                    or self._precland_waits()
                )
                and ap.armed
            ):
                # the companion stamps its answer with the frame's (exposure) time
                self._wait = FrameWait(
                    frame_id=self._frame_id - 1,
                    frame_time_ms=stamp_us // 1000,
                    deadline_wall_s=time.monotonic() + self.config.lockstep_timeout_s,
                )

    def _current_command(self) -> Command | None:
        ap = self.autopilot
        if ap.mode is not FlightMode.LAND:
            self._land_point_ne = None
        if not ap.armed:
            return None  # disarmed: motors off
        own = ap.flight_command(self.clock.time_s, self.sim.ground_truth)
        if own is not None:
            return own  # the profile's own (ArduCopter GUIDED_NOGPS, LAND)
        if ap.mode is FlightMode.OFFBOARD and ap.setpoint is not None:
            sp = ap.setpoint
            quat = self.sim.ground_truth().quat_wxyz if sp.attitude_quat_wxyz is not None else None
            return sp.command(quat)
        if self._land_cmd is None and ap.mode is FlightMode.PRECLAND:
            self._land_cmd = self._precland_command()  # on the autopilot's own estimate
        if self._land_cmd is None:  # LAND (or OFFBOARD without setpoint, impossible by rule)
            # PX4's AUTO.LAND lands where it was engaged, holding that position (ideally, on
            # ground truth, as HOLD holds ideally): not on the pad, which it does not know —
            # a failsafe landing must not count as a landing on the pad
            gt = self.sim.ground_truth()
            if self._land_point_ne is None:
                self._land_point_ne = np.array(gt.pos_ned_m[:2], float)
            rel = np.array(gt.pos_ned_m, float)
            rel[:2] -= self._land_point_ne
            self._land_cmd = self.land_controller.command(rel, gt.vel_ned_m_s, gt.quat_wxyz)
        return self._land_cmd

    def _control_step(self) -> bool:
        """The companion flies this control period: in flight, before touchdown, armed in
        OFFBOARD. Only these steps are the training record's control steps."""
        ap = self.autopilot
        return (
            self._flying
            and self.sim.contact is None
            and ap.armed
            and ap.mode is FlightMode.OFFBOARD
        )

    def _on_ground(self, truth: GroundTruth) -> bool:
        return self._flying and float(truth.pos_ned_m[2]) > _ON_GROUND_DOWN_M

    def _control_period(self) -> bool:
        """10 Hz checks. Returns False when the episode ended (nothing more this tick)."""
        assert self._episode is not None
        ap = self.autopilot
        truth = self.sim.ground_truth()
        ap.update(self.clock.time_s, on_ground=self._on_ground(truth))
        self._announce_events()
        if not self._flying and ap.taken_over:
            self._start_flight()
        self._land_cmd = None
        if self._episode_over():
            self._finish_episode()
            return self._next_episode()
        return True

    # ------------------------------------------------------------------ output

    def _send(self, msg: Any) -> None:
        # Packed (and signed) once; the ground station gets the same frame, as every PX4 link
        # sees the system's one message sequence.
        buf = self.endpoint.send(msg)
        if self.gcs_endpoint is not None:
            self.gcs_endpoint.send_bytes(buf)
        self._log_outbound(msg)

    def _total_stats(self) -> LinkStats:
        return LinkStats.total(*(e.stats for e in self._endpoints))

    def _statustext(self, severity: int, text: str) -> None:
        self._send(self.endpoint.mav.statustext_encode(severity, text[:50].encode()))
        self._event("statustext", text)

    def _announce_events(self) -> None:
        events = self.autopilot.pop_events()
        if not events:
            return
        for ev in events:
            self._event(ev.kind, ev.text)
            if ev.kind != "takeover" and ev.statustext:
                self._statustext(ev.severity, ev.text)
            log.info("autopilot: %s", ev.text)
        # PX4 shows a mode/arming change in the next heartbeat; MAVSDK waits for it: send now.
        self._send_heartbeat()

    def _send_heartbeat(self) -> None:
        self._send(self._build_heartbeat())

    def _send_frame(self) -> int | None:
        """Send this control period's camera frame; its ``time_us`` stamp, or None when the
        episode's ``frame_drop_prob`` lost it (nothing is sent; its frame id is skipped, as a
        camera's sequence number would be). With ``camera_latency_ms`` the frame goes out now
        but shows, and is stamped with, the scene ``latency`` earlier (its exposure)."""
        gt = self._sample_now().truth
        frame = self.sim.capture_frame(gt)
        frame_id = self._frame_id
        self._frame_id += 1
        stamp_us = None
        if frame.delivered:
            exposure_tick = max(self.clock.tick - self.sim.camera_latency_steps, 0)
            stamp_us = exposure_tick * 1_000_000 // self.clock.rate_hz
            imp = self.link_impairment
            for datagram in encode_frame(frame.image, frame_id % 2**32, stamp_us):
                if imp is None:
                    self._camera_sendto(datagram)
                else:
                    imp.streams["camera_tx"].offer(datagram, imp.clock(), imp.cut)
        else:
            self.camera_frames_dropped += 1
            self._event("camera_frame_dropped", f"frame {frame_id} lost (frame_drop_prob)")
        self._log_frame(frame_id, frame, gt)
        return stamp_us

    def _camera_sendto(self, datagram: bytes) -> None:
        try:
            self._camera_sock.sendto(datagram, self._camera_addr)
        except OSError:
            self.camera_tx_errors += 1


def _link_impairment(scenario: Scenario, config: SitlConfig) -> LinkImpairment | None:
    """The scenario's ``[link]`` with the ``--link-*`` flags over it; None for a perfect link.

    Raises:
        ConfigError: an impaired link in lockstep (delays are wall-clock time; a held answer
            would stop the lockstep clock instead of arriving late).
    """
    base = scenario.link or LinkConfig(source=scenario.source)
    cut = config.link_cut_at_s
    link = base.with_overrides(
        loss_prob=config.link_loss_prob,
        delay_ms=config.link_delay_ms,
        jitter_ms=config.link_jitter_ms,
        duplicate_prob=config.link_duplicate_prob,
        reorder_prob=config.link_reorder_prob,
        outage_s=None if cut is None else (cut, math.inf),
    )
    if not link.active:
        return None
    if config.lockstep:
        raise ConfigError(
            f"{scenario.source}: [link] (or --link-*) impairs a real-time link, but this SITL "
            "runs in lockstep, where a delayed answer would stop the clock instead of arriving "
            "late; run with --no-lockstep (visland fly --realtime), or drop the impairment"
        )
    return LinkImpairment(link, config.seed, time.monotonic)


def _initial_params(config: SitlConfig, hover_thrust_norm: float) -> AutopilotParams:
    """The profile's parameters at their defaults, then ``config.param`` (``--param``).

    Raises:
        SitlError: a value the parameter rejects (names it).
    """
    if config.autopilot == "ardupilot":
        params = ardupilot_params(hover_thrust_norm)
    else:
        params = AutopilotParams(mpc_thr_hover=hover_thrust_norm)
    for name, value in parse_param_overrides(config.param, config.autopilot):
        try:
            params = with_param(params, name, value, config.autopilot)
        except ValueError as exc:
            raise SitlError(f"--param {name}={value:g}: {exc}") from None
    return params


def _default_land_controller(vehicle: VehicleConfig, planet: Any) -> LandController:
    # AUTO.LAND flies the SITL's own cascade lander on ground truth (the law that
    # expert.cascade.CascadeLander wraps as a Policy); pass land_controller_factory to replace it.
    return CascadeLandController(vehicle, planet)


# --------------------------------------------------------------------------- entry points


def run_sitl(
    config: SitlConfig,
    land_controller_factory: Callable[[VehicleConfig, Any], LandController] | None = None,
) -> int:
    """Run the SITL until its episodes are flown; 0 when all were, 1 when stopped early
    (SIGINT/SIGTERM, ``max_wall_s``).

    SIGINT/SIGTERM stop it cleanly (flight logs closed) when called from the main thread.

    Raises:
        SitlPortInUseError: the MAVLink port is taken.
        SimError: any configuration error.
    """
    sitl = MavlinkSitl(config, land_controller_factory)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: sitl.stop())
    try:
        log.info(
            "SITL on udp %s:%d -> %s:%d, camera -> %s:%d, %s",
            config.host,
            sitl.endpoint.address[1],
            config.remote_host,
            config.remote_port,
            config.camera_host,
            config.camera_port,
            "lockstep" if config.lockstep else f"real time x{config.speed}",
        )
        if sitl.gcs_endpoint is not None:
            log.info(
                "ground-station link on udp %s:%d -> %s:%d",
                config.host,
                sitl.gcs_endpoint.address[1],
                config.gcs_remote_host,
                config.gcs_remote_port,
            )
        results = sitl.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    log.info("summary: %s", json.dumps(summarize(results)))
    return 0 if len(results) == config.episodes else 1


def main(argv: list[str] | None = None) -> int:
    """``python -m sitl_sim.mavlink_sitl`` (the CLI wires the same flags as ``visland sitl``)."""
    parser = argparse.ArgumentParser(prog="visland sitl", description=__doc__.split("\n")[0])
    add_sitl_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        return run_sitl(sitl_config_from_args(args))
    except SimError as exc:  # config, port in use, ...: one clear line, no traceback
        print(f"visland sitl: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
