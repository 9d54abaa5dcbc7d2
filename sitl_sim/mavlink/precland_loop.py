"""AUTO.PRECLAND in the MAVLink SITL: the autopilot's GPS-less estimate, the landing-target
estimator and the precision land (:mod:`sitl_sim.autopilot.nav_estimator`,
:mod:`sitl_sim.autopilot.precland`)
wired to the loop, LANDING_TARGET and the flight log.

:class:`PreclandLoop` is one part of :class:`~sitl_sim.mavlink.sitl.MavlinkSitl`: it reads the
flight state (autopilot, parameters, land controller), the tick's sensor sample and the clock,
answers through the publisher (STATUSTEXT) and writes its own flight-log records.

What the precision land reads: the IMU's specific force and the attitude estimate at 50 Hz
(the ticks HIGHRES_IMU and ATTITUDE stream on at their default rates, so the readings are the
streamed ones), the radar at the 10 Hz control rate (DISTANCE_SENSOR's ticks) and accepted
LANDING_TARGETs. Ground truth enters once: the estimator's initial velocity, with an error drawn
from the episode's own generator (``NavConfig.initial_vel_sigma_m_s``); the land detector
(``_on_ground``, auto-disarm) is the SITL's contact model, as for every mode.

**Lockstep**: in AUTO.PRECLAND nothing carries a setpoint, so a frame is answered by a
LANDING_TARGET stamped (``time_usec``) at or after the frame, or by the companion's
NAMED_VALUE_INT ``VL_FRAME`` (``time_boot_ms`` = the frame's time: "frame processed, no
target"). The clock waits for that answer only while the client paces it (an answer arrived
since the last timed-out wait): a companion killed mid-descent costs one ``lockstep_timeout_s``,
then the precision land runs free.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.contract import Command
from companion.contract.records import EventKind, PreclandRecord
from companion.contract.topics import TOPIC_PRECLAND
from sitl_sim.autopilot.nav_estimator import NavConfig, NavEstimator
from sitl_sim.autopilot.precland import (
    LandingTargetEstimator,
    LandingTargetRejected,
    PrecisionLand,
    measurement_from_landing_target,
)
from sitl_sim.autopilot.px4 import FlightMode
from sitl_sim.physics.dynamics import quat_from_euler

if TYPE_CHECKING:
    from sitl_sim.mavlink.clock import SimClock
    from sitl_sim.mavlink.config import SitlConfig
    from sitl_sim.mavlink.endpoint import Inbound
    from sitl_sim.mavlink.flight_log import FlightLog
    from sitl_sim.mavlink.publisher import Publisher
    from sitl_sim.mavlink.state import FlightState
    from sitl_sim.simulator import Simulator

__all__ = ["FRAME_MARKER_NAME", "NAV_RATE_HZ", "PreclandLoop"]

log = logging.getLogger("visland.sitl")

NAV_RATE_HZ = 50
"""The estimators' rate (PX4's landing_target_estimator runs at 50 Hz)."""
FRAME_MARKER_NAME = "VL_FRAME"
"""NAMED_VALUE_INT name of the landing-target companion's lockstep answer to a frame."""
_ALT_HOLD_GAIN = 1.0
"""Altitude-hold descent speed per metre of error (1/s), clamped to the ranges below."""
_MAX_CLIMB_M_S = 2.0
_MAX_HOLD_DESCENT_M_S = 3.0
_MAX_XY_ERROR_M = 10.0
"""The horizontal error the position loop sees is clamped to this (a slew limit: PX4 limits
the precision-land setpoint's speed to MPC_XY_CRUISE)."""
_NAV_SEED_KEY = 0x9C1A
"""Spawn key of the estimator's initial-error generator (apart from the simulator's streams)."""


@dataclass(eq=False, repr=False)
class PreclandLoop:
    """AUTO.PRECLAND's estimators, state machine and LANDING_TARGET handling.

    Args:
        config: the seed (the estimator's initial error) and the lockstep rules.
        state: the flight (autopilot mode and parameters, land controller, lockstep wait).
        publisher: the tick's sensor sample and STATUSTEXT.
        flight_log: where the precision land's records and events go.
        sim: the flight time its records carry.
        clock: the SITL clock.
        substeps: physics steps per control period (the radar is fused once per period).
        offboard_link: the name of the link that paces lockstep.
    """

    config: SitlConfig
    state: FlightState
    publisher: Publisher
    flight_log: FlightLog
    sim: Simulator
    clock: SimClock
    substeps: int
    offboard_link: str
    nav_config: NavConfig = field(init=False, default_factory=NavConfig)
    nav: NavEstimator | None = field(init=False, default=None)
    lte: LandingTargetEstimator | None = field(init=False, default=None)
    land: PrecisionLand | None = field(init=False, default=None)
    """The precision land's state machine (None: not in AUTO.PRECLAND, or no radar fix)."""
    landing_targets: Counter[str] = field(init=False, default_factory=Counter)
    """LANDING_TARGET counters this episode: received, accepted, gated, rejected, idle."""
    paced: bool = field(init=False, default=False)
    """A client answers frames in AUTO.PRECLAND (lockstep waits for it)."""
    _episode_index: int = field(init=False, default=0)
    _unsupported_frames: set[int] = field(init=False, default_factory=set)
    _nav_every: int = field(init=False)

    def __post_init__(self) -> None:
        self._nav_every = max(1, round(self.clock.rate_hz / NAV_RATE_HZ))

    def start_episode(self, index: int) -> None:
        """A new episode: no estimate, not paced, counters at zero."""
        self.reset()
        self._episode_index = index
        self.landing_targets = Counter()
        self._unsupported_frames = set()

    def reset(self, keep_paced: bool = False) -> None:
        """A new episode or flight: no estimate, no precision land (``keep_paced``: a client
        pacing the frozen HOLD paces the flight)."""
        self.nav = self.lte = self.land = None
        if not keep_paced:
            self.paced = False

    # ------------------------------------------------------------------ the loop

    def tick(self) -> None:
        """After the tick's streams: start/stop with the mode, run the estimators at 50 Hz."""
        active = self.state.flying and self.state.autopilot.mode is FlightMode.PRECLAND
        if not active:
            if self.land is not None:
                self.nav = self.lte = self.land = None
            return
        if self.land is None and not self._start():
            return
        if self.clock.phase % self._nav_every:
            return
        nav, lte = self.nav, self.lte
        assert nav is not None and lte is not None
        sample = self.publisher.sample()
        dt = self._nav_every / self.clock.rate_hz
        att = sample.attitude.attitude_rad
        nav.predict(dt, att, sample.imu.accel_frd_m_s2)
        lte.predict(dt, nav.accel_ned_m_s2, self.clock.time_s)
        lte.publish(nav, dt)
        if self.clock.phase % self.substeps == 0:
            nav.fuse_range(sample.range_m, att)

    def _start(self) -> bool:
        """Initialise the estimate and the precision land; False while the radar has no fix."""
        sample = self.publisher.sample()
        att = sample.attitude.attitude_rad
        rng_m = sample.range_m
        if not math.isfinite(rng_m):
            return False
        key = [self.config.seed, self._episode_index, _NAV_SEED_KEY]
        gen = np.random.default_rng(np.random.SeedSequence(key))
        sigma = self.nav_config.initial_vel_sigma_m_s
        # the one ground-truth input: the velocity at activation, with the estimator's error
        vel0 = sample.truth.vel_ned_m_s + gen.normal(0.0, 1.0, 3) * np.array([sigma, sigma, 0.1])
        height = rng_m * math.cos(float(att[0])) * math.cos(float(att[1]))
        self.nav = NavEstimator(self.nav_config, height, vel0)
        self.nav.attitude_rad = np.asarray(att, dtype=float).copy()
        params = self.state.autopilot.params
        self.lte = LandingTargetEstimator(params.ltest)
        self.land = PrecisionLand(params.pld, self.nav, self.lte, self.clock.time_s)
        self._announce()
        return True

    def _announce(self) -> None:
        if self.land is None:
            return
        for ev in self.land.pop_events():
            log.info("precland: %s", ev.text)
            self.publisher.statustext(ev.severity, ev.text)
            self.flight_log.event(EventKind.PRECLAND, f"{ev.state.value}: {ev.text}")

    def command(self) -> Command:
        """The precision land's command for this control period (10 Hz), on the estimate."""
        pl, nav = self.land, self.nav
        if pl is None or nav is None:
            # not initialised yet (no radar fix): level, hover thrust, until it is
            return Command(self.state.autopilot.params.mpc_thr_hover, np.zeros(3))
        sp = pl.update(self.clock.time_s)
        self._announce()
        err = nav.pos_ned_m[:2] - sp.north_east_m
        norm = float(np.linalg.norm(err))
        if norm > _MAX_XY_ERROR_M:
            err = err * (_MAX_XY_ERROR_M / norm)
        v_down = None
        if sp.altitude_m is not None:
            v_down = _ALT_HOLD_GAIN * (nav.altitude_m - sp.altitude_m)
            v_down = min(_MAX_HOLD_DESCENT_M_S, max(-_MAX_CLIMB_M_S, v_down))
        quat = quat_from_euler(*(float(a) for a in nav.attitude_rad))
        pos = np.array([err[0], err[1], -nav.altitude_m])
        vel = nav.vel_ned_m_s
        if sp.velocity_ne_m_s is not None:  # a moving target: fly the velocity relative to it
            vel = vel - np.array([sp.velocity_ne_m_s[0], sp.velocity_ne_m_s[1], 0.0])
        cmd = self.state.land_controller.command(pos, vel, quat, v_down_m_s=v_down)
        self._log(sp.altitude_m)
        return cmd

    def _log(self, hold_altitude_m: float | None) -> None:
        pl, nav, lte = self.land, self.nav, self.lte
        assert pl is not None and nav is not None and lte is not None
        now = self.clock.time_s
        seen = math.isfinite(lte.last_update_s)
        self.flight_log.write_record(
            TOPIC_PRECLAND,
            PreclandRecord(
                flight_time_s=self.sim.time_s,
                state=pl.state.value,
                search_count=pl.search_count,
                est_pos_ned_m=nav.pos_ned_m,
                est_vel_ned_m_s=nav.vel_ned_m_s,
                target_valid=lte.age_s(now) <= pl.params.btout_s,
                target_age_s=lte.age_s(now) if seen else None,
                target_rel_ne_m=lte.x[:, 0] if lte.initialised else None,
                target_rel_vel_ne_m_s=lte.x[:, 1] if lte.initialised else None,
                target_ne_m=pl.target_ne_m() if seen else None,
                approx_ne_m=pl.approx_ne_m,
                hold_altitude_m=hold_altitude_m,
            ),
        )

    # ------------------------------------------------------------------ messages

    def on_landing_target(self, msg: Any, inbound: Inbound) -> None:
        """LANDING_TARGET: read as PX4 does, fused when AUTO.PRECLAND runs, counted always; a
        malformed one is counted and ignored."""
        counts = self.landing_targets
        counts["received"] += 1
        ap = self.state.autopilot
        try:
            ap.check_landing_target(int(msg.frame), int(msg.position_valid), float(msg.distance))
            meas = measurement_from_landing_target(
                int(msg.frame),
                float(msg.angle_x),
                float(msg.angle_y),
                float(msg.distance),
                float(msg.x),
                float(msg.y),
                float(msg.z),
                int(msg.position_valid),
                self.clock.time_s,
            )
        except LandingTargetRejected as exc:
            counts["rejected"] += 1
            self.flight_log.event(EventKind.LANDING_TARGET_REJECTED, str(exc))
            frame = exc.unsupported_frame
            if frame is not None and frame not in self._unsupported_frames:
                self._unsupported_frames.add(frame)  # PX4 says it each time; once is enough
                self.publisher.statustext(2, str(exc))
            return
        self._answer_frame(msg.time_usec // 1000, inbound)
        nav, lte = self.nav, self.lte
        if nav is None or lte is None:
            counts["idle"] += 1  # not in AUTO.PRECLAND: nothing consumes it (PX4's LTE would)
            return
        if not lte.update(meas, nav):
            counts["gated"] += 1
            return
        counts["accepted"] += 1
        if ap.params.ltest.mode == 1:
            # LTEST_MODE Stationary: a static target's relative velocity is minus ours
            nav.fuse_velocity_ne(-lte.x[:, 1], lte.cov[:, 1, 1])

    def on_frame_marker(self, msg: Any, inbound: Inbound) -> None:
        """``VL_FRAME``: a landing-target companion's lockstep answer to a frame."""
        name = msg.name.decode() if isinstance(msg.name, bytes) else str(msg.name)
        if name.rstrip("\x00") == FRAME_MARKER_NAME:
            self._answer_frame(int(msg.time_boot_ms), inbound)

    def _answer_frame(self, stamp_ms: int, inbound: Inbound) -> None:
        if inbound.link != self.offboard_link:
            return  # lockstep is paced by the offboard link alone
        self.paced = True
        wait = self.state.wait
        if wait is not None and wait.answers(stamp_ms, self.config.lockstep_require_stamp):
            wait.answered = True

    def waits(self) -> bool:
        """In AUTO.PRECLAND, whether this frame waits for the companion's answer."""
        return self.state.autopilot.mode is FlightMode.PRECLAND and self.paced

    def wait_timed_out(self) -> None:
        """A frame went unanswered: in AUTO.PRECLAND the precision land runs free from now."""
        if self.waits():
            self.paced = False
            self.flight_log.event(
                EventKind.LOCKSTEP, "no answer to a frame in AUTO.PRECLAND: running free"
            )

    def record(self) -> dict[str, Any]:
        """The episode result's precision-land part."""
        pl = self.land
        return {
            "landing_target": dict(self.landing_targets),
            "precland_state": None if pl is None else pl.state.value,
        }
