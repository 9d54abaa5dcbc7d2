"""AUTO.PRECLAND in the MAVLink SITL: the autopilot's GPS-less estimate, the landing-target
estimator and the precision land (:mod:`sitl_sim.nav_estimator`, :mod:`sitl_sim.precland`)
wired to the loop, LANDING_TARGET and the flight log.

:class:`PreclandLoop` is a mixin of :class:`~sitl_sim.mavlink_sitl.MavlinkSitl`. It reads the
SITL's ``config``, ``sim``, ``autopilot``, ``params``, ``clock``, ``land_controller`` and the
tick's sensor sample (``_sample_now``), and answers through ``_statustext``, ``_event`` and
``_log``.

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
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.contract import Command
from companion.contract.topics import SCHEMA_PRECLAND, TOPIC_PRECLAND
from sitl_sim.autopilot import FlightMode
from sitl_sim.dynamics import quat_from_euler
from sitl_sim.nav_estimator import NavConfig, NavEstimator
from sitl_sim.precland import (
    LandingTargetEstimator,
    LandingTargetRejected,
    PrecisionLand,
    measurement_from_landing_target,
)

if TYPE_CHECKING:
    from sitl_sim.autopilot import Autopilot, AutopilotParams, LandController
    from sitl_sim.mavlink_endpoint import Inbound
    from sitl_sim.simulator import Simulator
    from sitl_sim.sitl_clock import FrameWait, SimClock
    from sitl_sim.sitl_config import SitlConfig

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


class PreclandLoop:
    """AUTO.PRECLAND's estimators, state machine and LANDING_TARGET handling."""

    config: SitlConfig
    sim: Simulator
    autopilot: Autopilot
    params: AutopilotParams
    clock: SimClock
    land_controller: LandController
    _wait: FrameWait | None
    _flying: bool

    def _init_precland(self) -> None:
        self.nav_config = NavConfig()
        self.nav: NavEstimator | None = None
        self.lte: LandingTargetEstimator | None = None
        self.precland: PrecisionLand | None = None
        self.landing_targets: Counter[str] = Counter()
        """LANDING_TARGET counters this episode: received, accepted, gated, rejected, idle."""
        self._precland_paced = False
        self._unsupported_frames: set[int] = set()
        self._nav_every = max(1, round(self.clock.rate_hz / NAV_RATE_HZ))

    def _reset_precland(self) -> None:
        """A new episode or flight: no estimate, no precision land, not paced."""
        self.nav = self.lte = self.precland = None
        self._precland_paced = False

    def _reset_precland_counters(self) -> None:
        self.landing_targets = Counter()
        self._unsupported_frames = set()

    # ------------------------------------------------------------------ the loop

    def _precland_tick(self) -> None:
        """After the tick's streams: start/stop with the mode, run the estimators at 50 Hz."""
        active = self._flying and self.autopilot.mode is FlightMode.PRECLAND
        if not active:
            if self.precland is not None:
                self._reset_precland_estimators()
            return
        if self.precland is None and not self._start_precland():
            return
        if self.clock.phase % self._nav_every:
            return
        nav, lte = self.nav, self.lte
        assert nav is not None and lte is not None
        sample = self._sample_now()
        dt = self._nav_every / self.clock.rate_hz
        att = sample.attitude.attitude_rad
        nav.predict(dt, att, sample.imu.accel_frd_m_s2)
        lte.predict(dt, nav.accel_ned_m_s2, self.clock.time_s)
        if self.clock.phase % self._substeps == 0:
            nav.fuse_range(sample.range_m, att)

    def _reset_precland_estimators(self) -> None:
        self.nav = self.lte = self.precland = None

    def _start_precland(self) -> bool:
        """Initialise the estimate and the precision land; False while the radar has no fix."""
        sample = self._sample_now()
        att = sample.attitude.attitude_rad
        rng_m = sample.range_m
        if not math.isfinite(rng_m):
            return False
        ep = self._episode
        key = [self.config.seed, ep.index if ep is not None else 0, _NAV_SEED_KEY]
        gen = np.random.default_rng(np.random.SeedSequence(key))
        sigma = self.nav_config.initial_vel_sigma_m_s
        # the one ground-truth input: the velocity at activation, with the estimator's error
        vel0 = sample.truth.vel_ned_m_s + gen.normal(0.0, 1.0, 3) * np.array([sigma, sigma, 0.1])
        height = rng_m * math.cos(float(att[0])) * math.cos(float(att[1]))
        self.nav = NavEstimator(self.nav_config, height, vel0)
        self.nav.attitude_rad = np.asarray(att, dtype=float).copy()
        self.lte = LandingTargetEstimator(self.params.ltest)
        self.precland = PrecisionLand(self.params.pld, self.nav, self.lte, self.clock.time_s)
        self._announce_precland()
        return True

    def _announce_precland(self) -> None:
        if self.precland is None:
            return
        for ev in self.precland.pop_events():
            log.info("precland: %s", ev.text)
            self._statustext(ev.severity, ev.text)
            self._event("precland", f"{ev.state.value}: {ev.text}")

    def _precland_command(self) -> Command:
        """The precision land's command for this control period (10 Hz), on the estimate."""
        pl, nav = self.precland, self.nav
        if pl is None or nav is None:
            # not initialised yet (no radar fix): level, hover thrust, until it is
            return Command(self.params.mpc_thr_hover, np.zeros(3))
        sp = pl.update(self.clock.time_s)
        self._announce_precland()
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
        cmd = self.land_controller.command(pos, nav.vel_ned_m_s, quat, v_down_m_s=v_down)
        self._log_precland(sp.altitude_m)
        return cmd

    def _log_precland(self, hold_altitude_m: float | None) -> None:
        pl, nav, lte = self.precland, self.nav, self.lte
        assert pl is not None and nav is not None and lte is not None
        now = self.clock.time_s
        seen = math.isfinite(lte.last_update_s)
        self._log(
            TOPIC_PRECLAND,
            SCHEMA_PRECLAND,
            {
                "flight_time_s": self.sim.time_s,
                "state": pl.state.value,
                "search_count": pl.search_count,
                "est_pos_ned_m": nav.pos_ned_m,
                "est_vel_ned_m_s": nav.vel_ned_m_s,
                "target_valid": lte.age_s(now) <= pl.params.btout_s,
                "target_age_s": lte.age_s(now) if seen else None,
                "target_rel_ne_m": lte.x[:, 0] if lte.initialised else None,
                "target_rel_vel_ne_m_s": lte.x[:, 1] if lte.initialised else None,
                "target_ne_m": pl.target_ne_m() if seen else None,
                "approx_ne_m": pl.approx_ne_m,
                "hold_altitude_m": hold_altitude_m,
            },
        )

    # ------------------------------------------------------------------ messages

    def _on_landing_target(self, msg: Any, inbound: Inbound) -> None:
        """LANDING_TARGET: read as PX4 does, fused when AUTO.PRECLAND runs, counted always."""
        counts = self.landing_targets
        counts["received"] += 1
        try:
            self.autopilot.check_landing_target(
                int(msg.frame), int(msg.position_valid), float(msg.distance)
            )
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
            self._event("landing_target_rejected", str(exc))
            frame = exc.unsupported_frame
            if frame is not None and frame not in self._unsupported_frames:
                self._unsupported_frames.add(frame)  # PX4 says it each time; once is enough
                self._statustext(2, str(exc))
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
        if self.params.ltest.mode == 1:
            # LTEST_MODE Stationary: a static target's relative velocity is minus ours
            nav.fuse_velocity_ne(-lte.x[:, 1], lte.cov[:, 1, 1])

    def _on_frame_marker(self, msg: Any, inbound: Inbound) -> None:
        name = msg.name.decode() if isinstance(msg.name, bytes) else str(msg.name)
        if name.rstrip("\x00") == FRAME_MARKER_NAME:
            self._answer_frame(int(msg.time_boot_ms), inbound)

    def _answer_frame(self, stamp_ms: int, inbound: Inbound) -> None:
        if inbound.link != self.endpoint.name:
            return  # lockstep is paced by the offboard link alone
        self._precland_paced = True
        wait = self._wait
        if wait is not None and wait.answers(stamp_ms, self.config.lockstep_require_stamp):
            wait.answered = True

    def _precland_waits(self) -> bool:
        """In AUTO.PRECLAND, whether this frame waits for the companion's answer."""
        return self.autopilot.mode is FlightMode.PRECLAND and self._precland_paced

    def _precland_wait_timed_out(self) -> None:
        if self.autopilot.mode is FlightMode.PRECLAND and self._precland_paced:
            self._precland_paced = False
            self._event("lockstep", "no answer to a frame in AUTO.PRECLAND: running free")

    def _precland_record(self) -> dict[str, Any]:
        """The episode result's precision-land part."""
        pl = self.precland
        return {
            "landing_target": dict(self.landing_targets),
            "precland_state": None if pl is None else pl.state.value,
        }
