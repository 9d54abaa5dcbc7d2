"""``visland sitl``: the simulator behind a PX4-like MAVLink 2 autopilot endpoint over real UDP.

One process, one thread, one clock. The loop advances the SITL clock one physics step (4 ms at
250 Hz) at a time; everything the outside world sees is stamped with that sim clock
(``time_boot_ms``/``time_usec`` = time since SITL start, monotonic across episodes; TIMESYNC
answers in sim ns). Per physics step:

1. physics (:class:`~sitl_sim.simulator.Simulator`) with the autopilot's command — or nothing
   while the vehicle is frozen (HOLD: before the take-over, and whenever HOLD is selected);
2. every stream whose interval is due (ATTITUDE, HIGHRES_IMU, ... at SET_MESSAGE_INTERVAL rates);
3. at each control period (10 Hz): offboard/land checks, episode end, the camera frame
   (UDP packets of :mod:`companion.contract.camera_packet`, stamped with its exposure time;
   not sent when the scenario's ``[sensors]`` loses it), the ground-truth log record; in
   lockstep and OFFBOARD, then wait for the companion's answer to a frame that was sent.

**Lockstep** (default): in OFFBOARD the clock stops after each camera frame until a
SET_ATTITUDE_TARGET arrives that was received after the frame was sent and is stamped
(``time_boot_ms``) at or after the frame's time (``lockstep_require_stamp``; turn it off for
clients that stamp with their own clock, e.g. MAVSDK), or until ``lockstep_timeout_s`` of wall
time passes (counted; the last setpoint holds, so a dead client meets COM_OF_LOSS_T after 10
frames), or until the vehicle is disarmed (not counted). Outside OFFBOARD nobody paces the loop:
LAND and the wait for disarm run as fast as the machine allows, and the frozen HOLD phase runs
at wall-clock speed (the companion's hand-shake happens in wall time). **Real time**
(``lockstep=False``): the clock follows the wall clock × ``speed`` throughout; the last setpoint
holds between messages.

**Episodes** (:mod:`sitl_sim.mavlink.episodes`) start in HOLD, armed, frozen; the flight starts
at the first control period after the vehicle is armed in a mode other than HOLD; one MCAP
flight log per episode (:mod:`sitl_sim.mavlink.flight_log`, a training record ``visland
relabel`` reads); ``first_episode`` lets parallel SITLs fly disjoint parts of one seed.

The SITL is composed of parts, each an object with its dependencies passed in (no part reaches
into another's attributes; what they share is :class:`~sitl_sim.mavlink.state.FlightState`):
:class:`~sitl_sim.mavlink.links.Links` (the sockets, signing, the impaired link; frames batched
into a datagram per link, held in lockstep flight until the frame nears: ``_FLUSH_LEAD``),
:class:`~sitl_sim.mavlink.publisher.Publisher` (streams, rates, builders, the tick's sensor
sample), :class:`~sitl_sim.mavlink.handlers.Handlers` (commands, setpoints, parameters),
:class:`~sitl_sim.mavlink.episodes.Episodes` (reset, flight start, scoring),
:class:`~sitl_sim.mavlink.flight_log.FlightLog` (the episode's MCAP log, its writes queued by
:class:`~sitl_sim.mavlink.log_queue.LogQueue` and run while the loop waits for the companion's
answer: same records, same order, off the frame's critical path) and
:class:`~sitl_sim.mavlink.precland_loop.PreclandLoop` (AUTO.PRECLAND and LANDING_TARGET).

:class:`MavlinkSitl` builds them and runs the loop (poll, tick, control period, the command
flown, the camera frame), timing its parts in flight (:class:`~companion.contract.perf.LoopPerf`,
logged at exit as one ``perf: {json}`` line, which ``visland bench sitl`` reads);
:mod:`sitl_sim.mavlink.config` holds :class:`SitlConfig` and its ``--flags``,
:mod:`sitl_sim.mavlink.clock` the sim clock, the lockstep frame wait and real-time pacing.
"""

from __future__ import annotations

import argparse
import json
import logging
import operator
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.contract import Command
from companion.contract.camera_packet import encode_frame
from companion.contract.perf import PERF_LINE_PREFIX, LoopPerf, pin_to_cpus
from companion.contract.records import EventKind
from companion.live.frame import PAPER_PAD_EXTENT_M
from sitl_sim.autopilot.ardupilot import new_autopilot
from sitl_sim.autopilot.land_controller import CascadeLandController
from sitl_sim.autopilot.px4 import FlightMode, LandController
from sitl_sim.config import SimConfig, VehicleConfig, load_sim, load_vehicle
from sitl_sim.errors import ConfigError, SimError
from sitl_sim.mavlink.clock import FrameWait, Pacer, SimClock
from sitl_sim.mavlink.config import (
    SitlConfig,
    add_sitl_arguments,
    initial_params,
    sitl_config_from_args,
)
from sitl_sim.mavlink.endpoint import LinkStats, SitlError
from sitl_sim.mavlink.episodes import Episodes, EpisodeSetup
from sitl_sim.mavlink.flight_log import FlightLog
from sitl_sim.mavlink.handlers import Handlers
from sitl_sim.mavlink.links import Links, link_impairment
from sitl_sim.mavlink.live import SitlLive
from sitl_sim.mavlink.log_queue import LogQueue
from sitl_sim.mavlink.precland_loop import PreclandLoop
from sitl_sim.mavlink.publisher import Publisher
from sitl_sim.mavlink.state import FlightState
from sitl_sim.metrics import EpisodeResult, summarize
from sitl_sim.physics.airframe import check_airframe_can_hover
from sitl_sim.scenario import InitialStateSampler, Scenario, load_scenario
from sitl_sim.simulator import Simulator

__all__ = ["MavlinkSitl", "main", "run_sitl"]

log = logging.getLogger("visland.sitl")

_FLUSH_LEAD = 5
"""In lockstep flight the telemetry batch is sent once at most this many physics steps (20 ms)
remain before the next frame, and with the frame: two datagrams a frame instead of one per
stream tick, each waking the companion (which then digests the batch while the SITL renders)."""


def _reads(path: str, doc: str | None = None) -> property:
    """A read-only property: ``self.<path>`` (dotted), read at each access."""
    return property(operator.attrgetter(path), doc=doc)


class MavlinkSitl:
    """The MAVLink SITL: build it (binds the ports), then :meth:`run` (blocking) or
    :meth:`stop` from another thread. Use as a context manager to release the ports.

    Args:
        config: the SitlConfig.
        land_controller_factory: builds the AUTO.LAND controller from (vehicle, planet), called
            again at an episode start whose vehicle differs (a scenario's ``[vehicle]``); the
            default is the privileged
            :class:`~sitl_sim.autopilot.land_controller.CascadeLandController` (ground truth in).

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
        self.clock = SimClock(sim_cfg.physics_rate_hz, sim_cfg.physics_dt_s)
        self._substeps = sim_cfg.substeps
        if self.scenario.vehicle is not None:
            check_airframe_can_hover(self.scenario.vehicle, self.vehicle, sim_cfg.planet)
        # AUTO.LAND flies the SITL's own cascade lander on ground truth (the law that
        # expert.cascade.CascadeLander wraps as a Policy) unless land_controller_factory is given
        factory = land_controller_factory or CascadeLandController
        params = initial_params(config, self.vehicle.hover_thrust_norm(sim_cfg.planet))
        self.state = FlightState(
            autopilot=new_autopilot(config.autopilot, params, armed=config.start_armed),
            land_controller=factory(self.vehicle, sim_cfg.planet),
        )
        self.sampler = InitialStateSampler(self.scenario, config.seed)
        self.link_impairment = link_impairment(self.scenario, config)
        """The impaired offboard + camera link (None: a perfect link)."""
        self._pacer = Pacer(self.clock.dt_s, config.speed)
        self.camera_frames_dropped = 0
        """Frames the scenario's ``frame_drop_prob`` lost (not sent)."""
        self.sim = Simulator(self.vehicle, sim_cfg, render=config.render)
        try:
            self.links = Links(config, self.link_impairment)
        except SitlError:
            self.sim.close()  # the pybullet client must not outlive a failed start
            raise
        self.perf = LoopPerf()
        """Wall time per part of the loop while flying, with the sim seconds and frames flown
        meanwhile (logged at exit as ``perf: {json}``)."""
        self.live = SitlLive(config.live) if config.live else None
        self.log_queue = LogQueue(self.perf)
        self.flight_log = FlightLog(clock=self.clock, open_writer=self.log_queue.open_writer)
        # the loop's parts share the simulator, its clock, the flight state and the flight log
        parts = dict(sim=self.sim, clock=self.clock, state=self.state, flight_log=self.flight_log)
        self.publisher = Publisher(config=config, links=self.links, sim_cfg=sim_cfg, **parts)
        self.log_queue.on_failure = self._log_stopped
        self.precland = PreclandLoop(
            config=config,
            publisher=self.publisher,
            substeps=self._substeps,
            offboard_link=self.links.offboard.name,
            **parts,
        )
        self.handlers = Handlers(
            config=config,
            links=self.links,
            publisher=self.publisher,
            precland=self.precland,
            **parts,
        )
        setup = EpisodeSetup(
            config=config,
            scenario=self.scenario,
            sampler=self.sampler,
            vehicle=self.vehicle,
            sim_cfg=sim_cfg,
            episode_timeout_s=config.episode_timeout_s or sim_cfg.episode_timeout_s,
            land_controller_factory=factory,
        )
        self.episodes = Episodes(
            setup=setup,
            links=self.links,
            publisher=self.publisher,
            handlers=self.handlers,
            precland=self.precland,
            **parts,
        )
        self._stop = threading.Event()
        self._land_cmd: Command | None = None
        """The command flown this control period when the autopilot flies its own (LAND,
        PRECLAND): computed once per period."""
        self._land_point_ne: np.ndarray | None = None
        """AUTO.LAND's landing point (north, east, pad frame): where the mode was engaged."""
        self._closed = False
        self._last_stats_log_wall = 0.0
        self._last_errors_logged = 0

    def _log_stopped(self, text: str) -> None:
        """The episode's log could not be written (a full disk): the flight goes on; the pilot
        and stderr are told."""
        log.warning("%s: the episode flies on without it", text)
        self.publisher.statustext(4, f"SITL {text}")  # MAV_SEVERITY_WARNING

    # ------------------------------------------------------------------ public

    time_s = _reads(
        "clock.time_s", "The SITL clock: sim seconds since start (MAVLink time_boot_ms / 1000)."
    )
    time_us = _reads("clock.time_us")
    autopilot = _reads("state.autopilot", "The autopilot flying the current episode.")
    params = _reads(
        "state.autopilot.params",
        "The autopilot's parameters now (PARAM_SET and the episode's airframe change them).",
    )
    results = _reads("episodes.results")
    lockstep_timeouts = _reads("state.lockstep_timeouts")
    pacing_overruns = _reads(
        "_pacer.overruns", "Times the paced clock fell behind the wall clock and re-anchored."
    )
    endpoint = _reads("links.offboard", "The offboard link.")
    gcs_endpoint = _reads(
        "links.gcs", "The ground-station link (None: ``gcs`` off, or its port was taken)."
    )
    stats = _reads(
        "links.offboard.stats", "The offboard link's counters (read-only from other threads)."
    )

    @property
    def gcs_stats(self) -> LinkStats | None:
        """The ground-station link's counters (None without that link)."""
        return self.links.gcs.stats if self.links.gcs is not None else None

    def stop(self) -> None:
        """Ask :meth:`run` to return (thread-safe); the current episode is logged as aborted."""
        self._stop.set()

    def run(self) -> list[EpisodeResult]:
        """Fly ``config.episodes`` episodes (or until :meth:`stop`); returns their results."""
        cfg = self.config
        wall0 = time.monotonic()
        state, perf = self.state, self.perf
        try:
            self.episodes.start(cfg.first_episode)
            while not self._stop.is_set() and not self.episodes.done:
                now = time.monotonic()
                perf.mark(self._physics_running())
                if cfg.max_wall_s is not None and now - wall0 > cfg.max_wall_s:
                    log.warning("max_wall_s = %.1f s reached: stopping", cfg.max_wall_s)
                    break
                self.links.release()
                self.poll()
                wait = state.wait
                if wait is not None:
                    # disarmed (the companion's disarm after touchdown crossed the frame): the
                    # frame has nobody to answer it and nothing to fly; the clock goes on
                    armed = self.autopilot.armed
                    if armed and wait.pending(now):
                        self._idle(min(wait.deadline_wall_s - now, 0.05))
                        continue
                    if armed and not wait.answered:
                        state.lockstep_timeouts += 1
                        self.precland.wait_timed_out()
                        if state.autopilot.runs_free_when_unanswered:
                            state.offboard_paced = False
                    state.wait = None
                # Nobody paces HOLD or real time: the wall clock does (lockstep flight runs free).
                paced = not self._physics_running() or not cfg.lockstep
                delay = self._pacer.delay_s(now, self.clock.tick, paced)
                if delay > 0:
                    self._idle(min(delay, 0.05))
                    continue
                self.tick_once()
                if paced or self._substeps - self.clock.phase % self._substeps <= _FLUSH_LEAD:
                    self.links.flush()  # lockstep flight: telemetry held until the frame nears
        finally:
            self.episodes.finish(aborted=not self.episodes.done)
            self.links.flush()
            self.log_queue.drain()
            perf.close()
            self.links.drain()
            self.close()
        return list(self.results)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.links.close()
        self.sim.close()
        if self.live is not None:
            self.live.close()

    def __enter__(self) -> MavlinkSitl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the loop

    def poll(self) -> None:
        """Read every link: log and act on what arrived, announce the autopilot's events."""
        perf, flight_log = self.perf, self.flight_log
        t = perf.now()
        queued = self.links.tx_messages
        for endpoint, accepted, errors in self.links.receive():
            t = perf.add("mavlink", t)
            for err in errors:
                flight_log.rx_error(err, endpoint.name)
            for inbound in accepted:
                t = perf.add("mavlink", t)
                flight_log.inbound(inbound)
                t = perf.add("log", t)
                self.handlers.dispatch(inbound, endpoint)
            t = perf.add("mavlink", t)
        self.publisher.announce_events()
        if self.links.tx_messages != queued:  # replies, events (and the telemetry held before)
            self.links.flush()
        perf.add("mavlink", t)
        self._maybe_log_stats()

    def tick_once(self) -> None:
        """One physics step, the streams due, and at a control period its checks and frame."""
        perf = self.perf
        running = self._physics_running()
        if running:
            cmd = self._current_command()
            if self.live is not None:
                self.live.flown(cmd)
            if self.clock.phase % self._substeps == 0:
                frame_id = self.state.frame_id - 1 if self._control_step() else None
                t = perf.now()
                self.flight_log.commands(self.sim.time_s, self.autopilot.mode_label, cmd, frame_id)
                perf.add("log", t)
            t = perf.now()
            self.sim.step_physics(cmd)
            perf.add("physics", t)
            perf.count("sim_s", self.clock.dt_s)
        if self.link_impairment is not None:  # the outage_s window, on flight time
            self.links.update_cut(self.sim.time_s, self.state.flying, self.flight_log)
        self.clock.tick += 1
        boundary = self.clock.phase % self._substeps == 0
        if boundary and not self._control_period():
            return  # the episode ended here; the next one starts at the next tick
        t = perf.now()
        self.publisher.emit_streams()
        perf.add("mavlink", t)
        if running:
            self.precland.tick()  # after the streams: it reads the readings they sent
        if boundary:
            stamp_us = self._send_frame()
            ap = self.autopilot
            if (
                stamp_us is not None  # a lost frame has no answer to wait for
                and self.config.lockstep
                and self._physics_running()
                and (
                    (ap.mode is FlightMode.OFFBOARD and self.state.offboard_paced)
                    or self.precland.waits()
                )
                and ap.armed
            ):
                # the companion stamps its answer with the frame's (exposure) time
                self.state.wait = FrameWait(
                    frame_id=self.state.frame_id - 1,
                    frame_time_ms=stamp_us // 1000,
                    deadline_wall_s=time.monotonic() + self.config.lockstep_timeout_s,
                )

    def _idle(self, timeout_s: float) -> None:
        """Nothing to simulate until a datagram arrives (the companion's answer) or
        ``timeout_s`` passes: write the queued log records meanwhile, else block on the links."""
        self.links.flush()  # nothing held while waiting
        t = self.perf.now()
        if self.log_queue.pending:
            self.log_queue.drain(stop=self.links.readable)
        else:
            self.links.sleep(timeout_s)
        self.perf.add("wait", t)

    def _physics_running(self) -> bool:
        return self.state.flying and self.autopilot.physics_running

    def _maybe_log_stats(self) -> None:
        """At most once a second of wall time: the links' counters, when errors grew."""
        now = time.monotonic()
        if now - self._last_stats_log_wall < 1.0:
            return
        self._last_stats_log_wall = now
        total = self.links.total_stats()
        errors = total.errors_comm + total.rx_unknown_msgid
        if errors != self._last_errors_logged:
            self._last_errors_logged = errors
            stats = self.links.stats_by_link()
            log.warning("MAVLink link errors so far: %s", stats)
            self.flight_log.link_stats(stats)

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
            self._land_cmd = self.precland.command()  # on the autopilot's own estimate
        if self._land_cmd is None:  # LAND (or OFFBOARD without setpoint, impossible by rule)
            # PX4's AUTO.LAND lands where it was engaged, holding that position (ideally, on
            # ground truth, as HOLD holds ideally): not on the pad, which it does not know —
            # a failsafe landing must not count as a landing on the pad
            gt = self.sim.ground_truth()
            if self._land_point_ne is None:
                self._land_point_ne = np.array(gt.pos_ned_m[:2], float)
            rel = np.array(gt.pos_ned_m, float)
            rel[:2] -= self._land_point_ne
            self._land_cmd = self.state.land_controller.command(rel, gt.vel_ned_m_s, gt.quat_wxyz)
        return self._land_cmd

    def _control_step(self) -> bool:
        """The companion flies this control period: in flight, before touchdown, armed in
        OFFBOARD. Only these steps are the training record's control steps."""
        ap = self.autopilot
        return (
            self.state.flying
            and self.sim.contact is None
            and ap.armed
            and ap.mode is FlightMode.OFFBOARD
        )

    def _control_period(self) -> bool:
        """10 Hz checks. Returns False when the episode ended (nothing more this tick)."""
        ap = self.autopilot
        ap.update(self.clock.time_s, on_ground=self.state.on_ground(self.sim))
        self.publisher.announce_events()
        if not self.state.flying and ap.taken_over:
            self.episodes.start_flight()
            self._land_point_ne = None  # AUTO.LAND's point: where it is engaged in this flight
        self._land_cmd = None
        if self.episodes.over():
            self.episodes.finish()
            self.episodes.start_next()
            return False
        return True

    def _send_frame(self) -> int | None:
        """Send this control period's camera frame; its ``time_us`` stamp, or None when the
        episode's ``frame_drop_prob`` lost it (nothing is sent; its frame id is skipped, as a
        camera's sequence number would be). With ``camera_latency_ms`` the frame goes out now
        but shows, and is stamped with, the scene ``latency`` earlier (its exposure)."""
        perf = self.perf
        gt = self.publisher.sample().truth
        t = perf.now()
        frame = self.sim.capture_frame(gt)
        t = perf.add("render", t)
        perf.count("frames")
        frame_id = self.state.frame_id
        self.state.frame_id += 1
        stamp_us = None
        if frame.delivered:
            exposure_tick = max(self.clock.tick - self.sim.camera_latency_steps, 0)
            stamp_us = exposure_tick * 1_000_000 // self.clock.rate_hz
            self.links.flush()  # the telemetry stamped at the frame's time goes first
            self.links.send_camera(encode_frame(frame.image, frame_id % 2**32, stamp_us))
            t = perf.add("camera", t)
            if self.live is not None:
                rng = self.sim.radar.true_range(gt.pos_ned_m, gt.quat_wxyz, gt.time_s)  # no draw
                episode = self.episodes.current
                pad = episode.pad_size_m if episode is not None else PAPER_PAD_EXTENT_M
                self.live.frame(frame, gt, self.autopilot.mode_label, rng, pad)
        else:
            self.camera_frames_dropped += 1
            self.flight_log.event(
                EventKind.CAMERA_FRAME_DROPPED, f"frame {frame_id} lost (frame_drop_prob)"
            )
        if self.flight_log.active:
            ap = self.autopilot
            observation = self.publisher.streamed_observation(frame_id, frame.exposure_time_s)
            self.flight_log.frame(
                frame_id,
                frame,
                gt,
                {"flying": self.state.flying, "mode": ap.mode_label, "armed": ap.armed},
                observation if self._control_step() else None,
            )
            perf.add("log", t)
        return stamp_us


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
    try:
        cpus = pin_to_cpus("sitl")  # VISLAND_SITL_CPUS
    except ValueError as exc:
        raise SitlError(str(exc)) from None
    sitl = MavlinkSitl(config, land_controller_factory)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: sitl.stop())
    try:
        log.info(
            "SITL on udp %s:%d -> %s:%d, camera -> %s:%d, %s%s",
            config.host,
            sitl.endpoint.address[1],
            config.remote_host,
            config.remote_port,
            config.camera_host,
            config.camera_port,
            "lockstep" if config.lockstep else f"real time x{config.speed}",
            "" if cpus is None else f", pinned to CPUs {cpus}",
        )
        if (gcs := sitl.gcs_endpoint) is not None:
            to = (config.host, gcs.address[1], config.gcs_remote_host, config.gcs_remote_port)
            log.info("ground-station link on udp %s:%d -> %s:%d", *to)
        results = sitl.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    log.info("summary: %s", json.dumps(summarize(results)))
    log.info("%s%s", PERF_LINE_PREFIX, json.dumps(sitl.perf.report()))
    return 0 if len(results) == config.episodes else 1


def main(argv: list[str] | None = None) -> int:
    """``python -m sitl_sim.mavlink`` (the CLI wires the same flags as ``visland sitl``)."""
    parser = argparse.ArgumentParser(prog="visland sitl", description=__doc__.split("\n")[0])
    add_sitl_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        return run_sitl(sitl_config_from_args(args))
    except (SimError, ConfigError) as exc:  # config, port in use, ...: one line, no traceback
        print(f"visland sitl: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
