"""The SITL's ``ardupilot`` profile: the autopilot behaves on the wire as ArduCopter 4.5 does for
a GPS-less companion-flown copter. No I/O, sim time in, like :class:`~sitl_sim.autopilot.px4.
Autopilot` (the ``px4`` profile), whose hooks it overrides.

Sources (paraphrased in ``shared/reference/mavlink_notes.md`` 1.4 and ``precland_notes.md`` 3):
ArduCopter ``GCS_Mavlink.cpp`` (``handle_message_set_attitude_target``, ``base_mode``),
``mode_guided.cpp`` (angle control and its timeout), ``mode.cpp`` (``set_mode``), ``events.cpp``
(GCS failsafe), ``mode_land.cpp`` and ``land_detector.cpp``.

* **Modes**: the SITL's internal modes are shown as ArduCopter's ``custom_mode`` numbers, the
  ``ardupilot`` profile's of the table the companion reads too
  (:mod:`companion.contract.autopilots`, ``ARDUPILOT``): HOLD (the frozen start, an ideal hold)
  = ALT_HOLD 2, OFFBOARD = GUIDED_NOGPS 20, LAND = LAND 9, and PRECLAND = LAND 9 too when
  ``PLND_ENABLED = 1`` and ``PLND_TYPE = 1`` (LAND uses the target).
  DO_SET_MODE (param1 CUSTOM_MODE_ENABLED, param2 = mode number) and SET_MODE (acknowledged
  with a COMMAND_ACK for command 11, as ArduPilot does). Modes that need a position estimate
  (GUIDED, LOITER, RTL, AUTO, ...) fail: MAV_RESULT_FAILED + "Mode change to LOITER failed:
  requires position"; unknown numbers: FAILED + "No such mode 99". Mode changes are not
  announced with STATUSTEXT (ArduPilot shows them in the HEARTBEAT only). No "setpoint must be
  streaming" rule: GUIDED_NOGPS is accepted at once and starts level, at zero climb rate.
  Manual modes (STABILIZE, ACRO, ...) need a pilot's sticks this SITL does not have: they fail
  with "... failed: needs a pilot (not modelled)" (a deviation: ArduCopter accepts them).
* **SET_ATTITUDE_TARGET** (:meth:`ArduCopter.setpoint_from_message`): ignored outside
  GUIDED_NOGPS; THROTTLE_IGNORE → ignored; a quaternion off unit length by > 1e-3 → ignored;
  the body rates are used only with all three rate bits clear (mixed bits → ignored and guided
  re-initialised: level, zero climb). ATTITUDE_IGNORE: rate control (ArduCopter ≥ 4.2
  ``set_angular_velocity``); otherwise the quaternion, with the rates as feed-forward.
  ``thrust``: with ``GUID_OPTIONS`` bit 3 collective thrust (clamped to [-1, 1], then [0, 1]
  by the motors); without it a climb-rate demand, 0.5 = hold, ``(t - 0.5) · 2 · WPNAV_SPEED_UP``
  above, ``(0.5 - t) · 2 · WPNAV_SPEED_DN`` down below, flown by :func:`climb_thrust`.
* **GUID_TIMEOUT**: no setpoint for ``GUID_TIMEOUT`` s in GUIDED_NOGPS → level (zero roll and
  pitch, the yaw held), zero body rates, zero climb rate, in GUIDED_NOGPS, until setpoints come
  back (ArduCopter's angle-control timeout; silent, as ArduPilot is).
* **LAND** without the precision land: level, descent at WPNAV_SPEED_DN above LAND_ALT_LOW and
  LAND_SPEED below, no horizontal control (ArduCopter ``land_nogps_run``): the vehicle drifts.
* **Land detector and disarm**: on the ground for 1 s (``LAND_DETECTOR_TRIGGER_SEC``) = landed;
  LAND disarms then, any other mode after ``DISARM_DELAY`` more. STATUSTEXT "Arming motors" /
  "Disarming motors".
* **GCS failsafe** (``FS_GCS_ENABLE`` ≠ 0, off by default): once a HEARTBEAT from
  ``SYSID_MYGCS`` (255) was seen, none for ``FS_GCS_TIMEOUT`` while armed and flying → LAND (every
  action needs a position but LAND) + "GCS Failsafe"; heartbeats back → "GCS Failsafe Cleared".
  The companion's own heartbeats (its sysid is the vehicle's) do not count, as in ArduPilot.
* **LANDING_TARGET**: only ``MAV_FRAME_BODY_FRD`` is read ("Plnd: Frame not supported"
  otherwise; LOCAL_FRD is not modelled), a position needs ``distance > 0``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.contract import Command, GroundTruth
from companion.contract.autopilots import ARDUPILOT, CopterMode
from companion.contract.records import EventKind
from sitl_sim.autopilot.ardupilot_params import NEEDS_POSITION
from sitl_sim.autopilot.precland import LandingTargetRejected, PldParams
from sitl_sim.autopilot.px4 import (
    Autopilot,
    AutopilotEvent,
    AutopilotParams,
    FlightMode,
    MavResult,
    Setpoint,
    SetpointRejected,
    TypeMask,
    _quat_mul,
)
from sitl_sim.physics.dynamics import euler_from_quat, quat_from_euler, quat_to_rotation

__all__ = [
    "ArduCopter",
    "ModeRefused",
    "ardupilot_params",
    "climb_thrust",
    "new_autopilot",
]

ANGLE_P_GAIN = 4.5
"""rad/s per rad of attitude error (ArduCopter ATC_ANG_RLL_P / _PIT_P / _YAW_P defaults)."""
VELZ_P_GAIN = 5.0
"""m/s² of vertical acceleration per m/s of climb-rate error (ArduCopter PSC_VELZ_P)."""
MAX_ACCEL_Z_M_S2 = 5.0
"""Vertical acceleration limit of the climb-rate controller (ArduCopter PILOT_ACCEL_Z 250 cm/s²
doubled: the position controller's own limit is higher than the pilot's)."""
GRAVITY_M_S2 = 9.80665
"""ArduPilot's GRAVITY_MSS (a compile-time constant: it does not know the planet)."""
LAND_DETECTOR_S = 1.0
"""ArduCopter LAND_DETECTOR_TRIGGER_SEC: on the ground this long = landed."""
_MAV_STATE_STANDBY, _MAV_STATE_ACTIVE, _MAV_STATE_CRITICAL = 3, 4, 5
_FLAG_CUSTOM, _FLAG_GUIDED, _FLAG_STABILIZE, _FLAG_MANUAL, _FLAG_ARMED = 1, 8, 16, 64, 128
_CUSTOM_OF = {
    FlightMode.HOLD: ARDUPILOT.hold,
    FlightMode.OFFBOARD: ARDUPILOT.offboard,
    FlightMode.LAND: ARDUPILOT.land,
    FlightMode.PRECLAND: ARDUPILOT.precland,
}
_MAV_FRAME_BODY_FRD = 12


@dataclass(frozen=True)
class ModeRefused:
    """A mode request ArduCopter refuses: MAV_RESULT_FAILED and this STATUSTEXT (warning)."""

    text: str


def ardupilot_params(hover_thrust_norm: float) -> AutopilotParams:
    """The ``ardupilot`` profile's parameters at their ArduCopter defaults: MOT_THST_HOVER the
    vehicle's hover thrust, PLND_XY_DIST_MAX 2.5 m, PLND_TIMEOUT 4 s, PLND_RET_MAX 4."""
    return AutopilotParams(
        mpc_thr_hover=hover_thrust_norm,
        pld=PldParams(hacc_rad_m=2.5, btout_s=4.0, max_srch=4),
    )


def climb_thrust(climb_up_m_s: float, truth: GroundTruth, hover_thrust_norm: float) -> float:
    """Collective thrust in [0, 1] that flies ``climb_up_m_s`` (ArduCopter's vertical velocity
    loop, PSC_VELZ_P, with the hover throttle MOT_THST_HOVER as its feed-forward and the lean
    angle compensated as ``AC_AttitudeControl`` does). Reads the vertical velocity of
    ``truth``: ArduPilot's EKF has barometer + accelerometer + rangefinder there, GPS or not."""
    v_up = -float(truth.vel_ned_m_s[2])
    accel = VELZ_P_GAIN * (climb_up_m_s - v_up)
    accel = min(MAX_ACCEL_Z_M_S2, max(-MAX_ACCEL_Z_M_S2, accel))
    tilt = max(0.5, float(quat_to_rotation(truth.quat_wxyz)[2, 2]))  # cos(roll)·cos(pitch)
    thrust = hover_thrust_norm * (1.0 + accel / GRAVITY_M_S2) / tilt
    return min(1.0, max(0.0, thrust))


def _angle_rates(
    quat_wxyz: np.ndarray, target_wxyz: np.ndarray, feed_forward: np.ndarray
) -> np.ndarray:
    """ArduCopter's angle P loop (ATC_ANG_*_P) on the error quaternion, + rate feed-forward."""
    q = np.asarray(quat_wxyz, dtype=float)
    err = _quat_mul(np.array([q[0], -q[1], -q[2], -q[3]]), target_wxyz)
    if err[0] < 0.0:
        err = -err  # shortest rotation
    return 2.0 * ANGLE_P_GAIN * err[1:] + feed_forward


class ArduCopter(Autopilot):
    """The ``ardupilot`` profile (module docstring). ``params.ardu`` holds ArduCopter's own
    parameters; ``params.mpc_thr_hover`` is MOT_THST_HOVER."""

    profile = ARDUPILOT.name
    hover_param = ARDUPILOT.hover_param
    precland_needs_range = False  # ArduCopter's LAND works without a rangefinder
    runs_free_when_unanswered = True
    acks_set_mode = True
    _armed_text = "Arming motors"

    def __init__(self, params: AutopilotParams, *, armed: bool = True) -> None:
        super().__init__(params, armed=armed)
        self._guided_since_s = 0.0
        """When GUIDED_NOGPS was entered or re-initialised (its level-hold start)."""
        self._level_yaw_rad: float | None = None
        """The yaw held while levelled (the yaw when the level hold began)."""
        self.guided_timed_out = False
        """GUIDED_NOGPS is levelled because no setpoint came for GUID_TIMEOUT."""
        self._landed_s: float | None = None
        self._gcs_heartbeat_s: float | None = None
        self.gcs_failsafe = False

    # ------------------------------------------------------------------ identity

    @property
    def mode_label(self) -> str:
        return _CUSTOM_OF[self.mode].label

    def heartbeat(self) -> tuple[int, int, int, int]:
        """ArduCopter's ``base_mode``: STABILIZE | MANUAL_INPUT | CUSTOM_MODE (81), + GUIDED
        while the horizontal position controller runs (the precision land), + SAFETY_ARMED."""
        flags = _FLAG_CUSTOM | _FLAG_STABILIZE | _FLAG_MANUAL
        if self.mode is FlightMode.PRECLAND:
            flags |= _FLAG_GUIDED
        if self.armed:
            flags |= _FLAG_ARMED
        if self.armed and self.gcs_failsafe:
            state = _MAV_STATE_CRITICAL
        else:
            state = _MAV_STATE_ACTIVE if self.armed else _MAV_STATE_STANDBY
        return ARDUPILOT.mav_autopilot, flags, _CUSTOM_OF[self.mode].custom_mode, state

    # ------------------------------------------------------------------ modes

    def mode_for_command(self, param2: float, param3: float) -> FlightMode | ModeRefused:
        return self.mode_for_custom(int(param2))

    def mode_for_custom(self, custom: int) -> FlightMode | ModeRefused:  # type: ignore[override]
        number = CopterMode.from_custom(custom)
        if number is None:
            return ModeRefused(f"No such mode {custom}")
        if number is ARDUPILOT.offboard:
            return FlightMode.OFFBOARD
        if number is ARDUPILOT.hold:
            return FlightMode.HOLD
        if number is ARDUPILOT.land:
            return self.land_mode()
        why = "requires position" if number in NEEDS_POSITION else "needs a pilot (not modelled)"
        return ModeRefused(f"Mode change to {number.name} failed: {why}")

    def land_mode(self) -> FlightMode:
        return FlightMode.PRECLAND if self.params.ardu.precland else FlightMode.LAND

    def request_mode(self, mode, now_s: float) -> MavResult:  # type: ignore[override]
        if isinstance(mode, ModeRefused):
            self._events.append(AutopilotEvent(EventKind.MODE_REFUSED, mode.text, 4))
            return MavResult.FAILED
        if not isinstance(mode, FlightMode):
            return MavResult.FAILED
        self._enter(mode, now_s)
        self._maybe_take_over()
        return MavResult.ACCEPTED

    def _enter(self, mode: FlightMode, now_s: float, why: str = "") -> None:
        if mode is self.mode:
            return  # ArduCopter: setting the current mode again changes nothing
        self.mode = mode
        if mode is FlightMode.OFFBOARD:
            self._guided_init(now_s)
        text = f"mode {self.mode_label}" + (f" ({why})" if why else "")
        self._events.append(AutopilotEvent(EventKind.MODE, text, 6, statustext=False))

    def _guided_init(self, now_s: float) -> None:
        """ArduCopter ``angle_control_start``: level, zero climb rate, from now."""
        self.setpoint = None
        self._guided_since_s = now_s
        self._level_yaw_rad = None
        self.guided_timed_out = False

    # ------------------------------------------------------------------ setpoints

    def setpoint_from_message(
        self, type_mask, q, body_rates, thrust, thrust_body, time_s
    ) -> Setpoint | None:
        """SET_ATTITUDE_TARGET as ArduCopter's GUIDED_NOGPS reads it (module docstring).

        Returns None outside GUIDED_NOGPS (ArduPilot ignores it silently).

        Raises:
            SetpointRejected: a message ArduCopter ignores in GUIDED_NOGPS (names why).
        """
        if self.mode is not FlightMode.OFFBOARD:
            return None
        mask = int(type_mask) & 0xFF
        if mask & TypeMask.THROTTLE_IGNORE:
            raise SetpointRejected(f"type_mask {mask}: THROTTLE_IGNORE (ArduCopter ignores it)")
        attitude = None
        if not mask & TypeMask.ATTITUDE_IGNORE:
            quat = np.array([float(v) for v in q])
            norm = float(np.linalg.norm(quat))
            if not (math.isfinite(norm) and abs(norm - 1.0) <= 1e-3):
                raise SetpointRejected(f"attitude quaternion {quat.tolist()} is not unit length")
            attitude = quat
        rate_bits = mask & 7
        if rate_bits == 0:
            rates = np.array([float(v) for v in body_rates])
            if not np.all(np.isfinite(rates)):
                raise SetpointRejected(f"non-finite body rates {rates.tolist()}")
        elif rate_bits == 7:
            rates = np.zeros(3)
        else:
            self._guided_init(time_s)  # ArduCopter: mode_guided.init(true)
            raise SetpointRejected(
                f"type_mask {mask}: some body rates ignored, not all (ArduCopter re-initialises "
                "guided: level, zero climb)"
            )
        thrust = float(thrust)
        if not math.isfinite(thrust):
            raise SetpointRejected(f"non-finite thrust {thrust}")
        ardu = self.params.ardu
        thrust_norm = min(1.0, max(0.0, thrust))  # thrust: [-1, 1], then no reverse thrust
        climb: float | None = None
        if not ardu.thrust_is_thrust:
            if thrust_norm > 0.5:
                climb = (thrust_norm - 0.5) * 2.0 * ardu.wpnav_speed_up_cm_s / 100.0
            elif thrust_norm < 0.5:
                climb = -(0.5 - thrust_norm) * 2.0 * ardu.wpnav_speed_dn_cm_s / 100.0
            else:
                climb = 0.0
        return Setpoint(time_s, thrust_norm, rates, attitude, mask, climb_rate_up_m_s=climb)

    def on_setpoint(self, setpoint: Setpoint) -> None:
        self.setpoint = setpoint
        if self.guided_timed_out:
            self.guided_timed_out = False
            self._level_yaw_rad = None
            self._events.append(
                AutopilotEvent(
                    EventKind.GUIDED, "setpoints back: GUIDED_NOGPS follows them", 6, False
                )
            )

    # ------------------------------------------------------------------ flying

    def flight_command(self, now_s: float, truth: Callable[[], GroundTruth]) -> Command | None:
        if self.mode is FlightMode.OFFBOARD:
            return self._guided_command(now_s, truth)
        if self.mode is FlightMode.LAND:
            return self._land_command(truth())
        return None  # PRECLAND: the SITL's precision land; HOLD: frozen

    def _guided_command(self, now_s: float, truth: Callable[[], GroundTruth]) -> Command:
        sp = self.setpoint
        hover = self.params.mpc_thr_hover
        last_s = self._guided_since_s if sp is None else max(sp.time_s, self._guided_since_s)
        if sp is None or now_s - last_s > self.params.ardu.guid_timeout_s:
            if sp is not None and not self.guided_timed_out:
                self.guided_timed_out = True
                self._events.append(
                    AutopilotEvent(
                        EventKind.GUIDED_TIMEOUT,
                        f"no setpoint for GUID_TIMEOUT = {self.params.ardu.guid_timeout_s:.1f} s:"
                        " level, zero climb rate",
                        4,
                        statustext=False,  # ArduCopter says nothing
                    )
                )
            return self._level_command(truth(), 0.0)
        if sp.attitude_quat_wxyz is None and sp.climb_rate_up_m_s is None:
            return sp.command()  # rates + thrust (mask 128, GUID_OPTIONS 8): the Command itself
        gt = truth()
        if sp.attitude_quat_wxyz is None:
            rates = sp.rate_frd_rad_s
        else:
            rates = _angle_rates(gt.quat_wxyz, sp.attitude_quat_wxyz, sp.rate_frd_rad_s)
        if sp.climb_rate_up_m_s is None:
            thrust = sp.thrust_norm
        else:
            thrust = climb_thrust(sp.climb_rate_up_m_s, gt, hover)
        return Command(thrust, rates)

    def _level_command(self, gt: GroundTruth, climb_up_m_s: float) -> Command:
        """Level at the held yaw, zero body-rate feed-forward, flying ``climb_up_m_s``."""
        if self._level_yaw_rad is None:
            self._level_yaw_rad = float(euler_from_quat(gt.quat_wxyz)[2])
        target = quat_from_euler(0.0, 0.0, self._level_yaw_rad)
        rates = _angle_rates(gt.quat_wxyz, target, np.zeros(3))
        return Command(climb_thrust(climb_up_m_s, gt, self.params.mpc_thr_hover), rates)

    def _land_command(self, gt: GroundTruth) -> Command:
        ardu = self.params.ardu
        altitude_cm = -float(gt.pos_ned_m[2]) * 100.0
        speed = (
            ardu.wpnav_speed_dn_cm_s
            if altitude_cm > ardu.land_alt_low_cm
            else (ardu.land_speed_cm_s)
        )
        return self._level_command(gt, -speed / 100.0)

    # ------------------------------------------------------------------ checks

    def update(self, now_s: float, *, on_ground: bool) -> None:
        """10 Hz: the GCS failsafe, the land detector and auto-disarm (no offboard-loss rule:
        GUIDED_NOGPS levels on GUID_TIMEOUT, in :meth:`flight_command`)."""
        self._check_gcs(now_s)
        if not (self.armed and self.physics_running and on_ground):
            self._landed_s = None
            return
        if self._landed_s is None:
            self._landed_s = now_s
        on_ground_s = now_s - self._landed_s
        if on_ground_s < LAND_DETECTOR_S - 1e-9:
            return
        if self.mode in (FlightMode.LAND, FlightMode.PRECLAND):
            self._disarm("landed in LAND")  # mode_land: disarm once landed
        elif (
            self.params.ardu.disarm_delay_s > 0
            and on_ground_s >= LAND_DETECTOR_S + self.params.ardu.disarm_delay_s - 1e-9
        ):
            self._disarm("DISARM_DELAY")  # auto_disarm_check

    def _disarm(self, text: str) -> None:
        super()._disarm("Disarming motors")  # ArduPilot's one line, whatever the reason

    def on_heartbeat(self, sysid: int, compid: int, now_s: float) -> None:
        if sysid == self.params.ardu.sysid_mygcs:
            self._gcs_heartbeat_s = now_s

    def _check_gcs(self, now_s: float) -> None:
        ardu = self.params.ardu
        if ardu.fs_gcs_enable == 0 or self._gcs_heartbeat_s is None:
            return
        lost = now_s - self._gcs_heartbeat_s > ardu.fs_gcs_timeout_s
        if lost and not self.gcs_failsafe and self.armed and self.physics_running:
            self.gcs_failsafe = True
            self._events.append(AutopilotEvent(EventKind.FAILSAFE, "GCS Failsafe", 4))
            if self.mode not in (FlightMode.LAND, FlightMode.PRECLAND):
                self._enter(self.land_mode(), now_s, "GCS failsafe")
        elif not lost and self.gcs_failsafe:
            self.gcs_failsafe = False
            self._events.append(AutopilotEvent(EventKind.FAILSAFE, "GCS Failsafe Cleared", 4))

    def check_landing_target(self, frame: int, position_valid: int, distance: float) -> None:
        if frame != _MAV_FRAME_BODY_FRD:
            raise LandingTargetRejected("Plnd: Frame not supported", unsupported_frame=frame)
        if position_valid == 1 and not distance > 0:
            raise LandingTargetRejected(
                f"LANDING_TARGET position with distance {distance}: ArduPilot needs > 0"
            )


def new_autopilot(profile: str, params: AutopilotParams, *, armed: bool) -> Autopilot:
    """The autopilot of a SITL profile (``px4`` or ``ardupilot``)."""
    if profile == "ardupilot":
        return ArduCopter(params, armed=armed)
    if profile == "px4":
        return Autopilot(params, armed=armed)
    raise ValueError(f"autopilot profile {profile!r}; expected 'px4' or 'ardupilot'")
