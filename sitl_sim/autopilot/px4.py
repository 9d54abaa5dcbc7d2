"""The PX4-like autopilot logic of the MAVLink SITL: modes, arming, offboard rules, failsafe.

No I/O and no wall clock here: every method takes the SITL's sim time (``now_s``), so the state
machine is a pure function of the messages it was given and can be unit-tested without sockets.
What it models (PX4 behaviour, ``shared/reference/mavlink_notes.md`` sections 6 and 11):

* **Modes** — PX4 custom modes, ``custom_mode = (main << 16) | (sub << 24)``, numbered as in
  the table the companion reads too (:mod:`companion.contract.autopilots`, profile ``PX4``):
  HOLD (AUTO.LOITER, the episode's start: the vehicle is *frozen* at its state, an ideal position
  hold), OFFBOARD (the companion flies SET_ATTITUDE_TARGET setpoints) and LAND (AUTO.LAND: the
  SITL's own land controller, on ground truth, landing where the mode was engaged, as PX4's —
  not on the pad, which the autopilot does not know), PRECLAND (AUTO.PRECLAND: the precision land
  of :mod:`sitl_sim.autopilot.precland` on LANDING_TARGET, on the autopilot's own estimate). Other
  PX4
  modes (POSCTL, ALTCTL, ...) need GPS or sticks and are refused with TEMPORARILY_REJECTED,
  as PX4 refuses a mode whose requirements fail.
* **Offboard rules** — OFFBOARD is accepted only while a setpoint arrived within
  ``COM_OF_LOSS_T`` (sim time); once in OFFBOARD, a silence longer than ``COM_OF_LOSS_T`` switches
  to the ``COM_OBL_RC_ACT`` action (4 = Land, the only action modelled).
* **Take-over** — the vehicle stays frozen at its initial state until it is armed in a mode other
  than HOLD; from then on physics runs (HOLD pauses it again).
* **Auto-disarm** — after ``COM_DISARM_LAND`` seconds on the ground.
* **Setpoints** — SET_ATTITUDE_TARGET ``type_mask`` as PX4's ``mavlink_receiver.cpp`` reads it:
  see :func:`setpoint_from_target`.
"""

from __future__ import annotations

import enum
import functools
import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from companion.contract import Command
from companion.contract.autopilots import (
    FORCE_DISARM_MAGIC,
    PX4,
    PX4_AUTO_SUB_MODES,
    Px4MainMode,
    Px4Mode,
)
from companion.contract.records import EventKind
from sitl_sim.autopilot.ardupilot_params import ArduParams
from sitl_sim.autopilot.precland import LteParams, PldParams

__all__ = [
    "COM_OBL_RC_ACT_LAND",
    "FORCE_DISARM_MAGIC",
    "Autopilot",
    "AutopilotEvent",
    "AutopilotParams",
    "FlightMode",
    "LandController",
    "MavResult",
    "Setpoint",
    "SetpointRejected",
    "TypeMask",
    "base_mode",
    "custom_mode",
    "mode_from_custom",
    "setpoint_from_target",
]

_MAV_STATE_STANDBY = 3
_MAV_STATE_ACTIVE = 4

COM_OBL_RC_ACT_LAND = 4
"""COM_OBL_RC_ACT value 'Land' (PX4 commander_params.yaml)."""

ATTITUDE_P_GAIN = 6.5
"""rad/s per rad of attitude error in the attitude-setpoint branch (PX4 MC_ROLL_P/MC_PITCH_P)."""
YAW_P_GAIN = 2.8
"""rad/s per rad of yaw error (PX4 MC_YAW_P)."""


class MavResult(enum.IntEnum):
    """MAV_RESULT values a COMMAND_ACK carries (pymavlink 2.4.50 lacks CANCELLED)."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


class FlightMode(enum.Enum):
    """The modes this autopilot implements, valued by their PX4 (main_mode, sub_mode): the
    ``px4`` profile's modes of the shared table."""

    HOLD = PX4.hold.value  # AUTO.LOITER, shown as "Hold"
    OFFBOARD = PX4.offboard.value
    LAND = PX4.land.value  # AUTO.LAND
    # AUTO.PRECLAND (sitl_sim.autopilot.precland, on its own estimate)
    PRECLAND = PX4.precland.value

    @property
    def px4(self) -> Px4Mode:
        """The PX4 mode of the table."""
        return Px4Mode(self.value)

    @property
    def label(self) -> str:
        return self.px4.label


_FLIGHT_MODE_OF = {mode.px4: mode for mode in FlightMode}


def custom_mode(mode: FlightMode) -> int:
    """PX4 ``custom_mode``: ``(main << 16) | (sub << 24)`` (e.g. OFFBOARD = 393216)."""
    return mode.px4.custom_mode


def base_mode(mode: FlightMode, armed: bool) -> int:
    """PX4 heartbeat base_mode: CUSTOM_MODE_ENABLED | AUTO | GUIDED | STABILIZE (+ SAFETY_ARMED).

    All three modes here are PX4 'auto' modes: 29 disarmed, 157 armed.
    """
    flags = 1 | 4 | 8 | 16
    return flags | (128 if armed else 0)


def mode_from_custom(main: int, sub: int) -> FlightMode | bool | None:
    """The FlightMode a (main, sub) request names.

    Returns the mode; ``False`` for a real PX4 mode this vehicle cannot fly (it needs GPS or
    RC sticks: refuse with TEMPORARILY_REJECTED); ``None`` for numbers that name no PX4 mode
    (DENIED).
    """
    mode = _FLIGHT_MODE_OF.get(Px4Mode.from_main_sub(main, sub))
    if mode is not None:
        return mode
    if main == Px4MainMode.AUTO:
        return False if sub in PX4_AUTO_SUB_MODES else None
    try:
        Px4MainMode(main)
    except ValueError:
        return None
    return False


class TypeMask(enum.IntFlag):
    """ATTITUDE_TARGET_TYPEMASK bits (set = ignore that field, except THRUST_BODY_SET)."""

    BODY_ROLL_RATE_IGNORE = 1
    BODY_PITCH_RATE_IGNORE = 2
    BODY_YAW_RATE_IGNORE = 4
    THRUST_BODY_SET = 32
    THROTTLE_IGNORE = 64
    ATTITUDE_IGNORE = 128


class SetpointRejected(ValueError):
    """A SET_ATTITUDE_TARGET that PX4 would ignore (names the reason); it does not count as a
    proof of life for the offboard rules."""


@dataclass(frozen=True)
class Setpoint:
    """One accepted SET_ATTITUDE_TARGET.

    Attributes:
        time_s: SITL sim time it was received.
        thrust_norm: collective thrust in [0, 1] of the total maximum thrust.
        rate_frd_rad_s: (3,) body-rate setpoint (rates branch) or feed-forward (attitude branch;
            only the yaw component is used there); made read-only here (the rate loop holds it
            for many physics steps).
        attitude_quat_wxyz: (4,) attitude setpoint (NED -> FRD rotation as MAVLink's q), or None
            for the rates branch (type_mask 128).
        type_mask: the raw type_mask, kept for ATTITUDE_TARGET and the log.
    """

    time_s: float
    thrust_norm: float
    rate_frd_rad_s: np.ndarray
    attitude_quat_wxyz: np.ndarray | None
    type_mask: int
    climb_rate_up_m_s: float | None = None
    """ArduCopter's climb-rate reading of ``thrust`` (GUID_OPTIONS bit 3 clear): the demanded
    climb rate, m/s up; ``thrust_norm`` is then the raw field. None: thrust is thrust."""

    def __post_init__(self) -> None:
        self.rate_frd_rad_s.setflags(write=False)

    @functools.cached_property
    def _rates_command(self) -> Command:
        # Built once: the rates branch is held for many physics steps.
        return Command(self.thrust_norm, self.rate_frd_rad_s)

    def command(self, quat_wxyz: np.ndarray | None = None) -> Command:
        """The rate-loop Command now; the attitude branch needs the current attitude."""
        if self.attitude_quat_wxyz is None:
            return self._rates_command
        if quat_wxyz is None:
            raise ValueError("an attitude setpoint needs the current attitude")
        return Command(self.thrust_norm, _attitude_rates(quat_wxyz, self))


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def _attitude_rates(quat_wxyz: np.ndarray, sp: Setpoint) -> np.ndarray:
    """PX4-style attitude P loop: body rates from the error quaternion ``q^-1 * q_sp``."""
    q = np.asarray(quat_wxyz, dtype=float)
    q_conj = np.array([q[0], -q[1], -q[2], -q[3]])
    err = _quat_mul(q_conj, sp.attitude_quat_wxyz)  # type: ignore[arg-type]
    if err[0] < 0.0:
        err = -err  # shortest rotation
    gains = np.array([ATTITUDE_P_GAIN, ATTITUDE_P_GAIN, YAW_P_GAIN])
    rates = 2.0 * gains * err[1:]
    rates[2] += sp.rate_frd_rad_s[2]  # yaw-rate feed-forward (zero when ignored)
    return rates


def setpoint_from_target(
    type_mask: int,
    q: tuple[float, float, float, float] | list[float],
    body_rates: tuple[float, float, float],
    thrust: float,
    thrust_body: tuple[float, float, float] | None,
    time_s: float,
    previous_thrust: float | None,
) -> Setpoint:
    """Interpret SET_ATTITUDE_TARGET fields as PX4 does for a multicopter.

    * ATTITUDE_IGNORE (128) set: the **rates branch**, taken only if neither roll nor pitch rate
      is ignored (PX4 ignores the message otherwise); an ignored yaw rate means 0 rad/s.
      ``type_mask = 128`` (what MAVSDK ``set_attitude_rate`` and the companion send) is the
      :class:`~companion.contract.Command` contract exactly.
    * ATTITUDE_IGNORE clear: the **attitude branch**: ``q`` (normalised) is tracked with a P loop
      (:data:`ATTITUDE_P_GAIN`), body_yaw_rate is a feed-forward unless YAW_RATE_IGNORE.
    * Thrust: THRUST_BODY_SET (32) uses ``-thrust_body[2]`` (body z points down; the x/y parts
      cannot be produced by a quadrotor and are dropped, as PX4 does); else THROTTLE_IGNORE (64)
      keeps the previous thrust; else ``thrust``. Clamped to [0, 1] like PX4's actuator limits.

    Raises:
        SetpointRejected: ignored branch, non-finite values, zero quaternion, or no thrust known.
    """
    mask = TypeMask(type_mask & 0xFF)
    rates = np.array([float(v) for v in body_rates])
    if TypeMask.BODY_YAW_RATE_IGNORE in mask:
        rates[2] = 0.0
    if TypeMask.THRUST_BODY_SET in mask:
        if thrust_body is None:
            raise SetpointRejected("type_mask has THRUST_BODY_SET but thrust_body is missing")
        thrust_value: float | None = -float(thrust_body[2])
    elif TypeMask.THROTTLE_IGNORE in mask:
        thrust_value = previous_thrust
        if thrust_value is None:
            raise SetpointRejected("THROTTLE_IGNORE before any thrust was set")
    else:
        thrust_value = float(thrust)
    if not math.isfinite(thrust_value):
        raise SetpointRejected(f"non-finite thrust {thrust_value}")
    thrust_norm = min(1.0, max(0.0, thrust_value))
    attitude: np.ndarray | None = None
    if TypeMask.ATTITUDE_IGNORE in mask:
        if mask & (TypeMask.BODY_ROLL_RATE_IGNORE | TypeMask.BODY_PITCH_RATE_IGNORE):
            raise SetpointRejected(
                f"type_mask {type_mask}: attitude and roll/pitch rate both ignored (PX4 drops it)"
            )
        if not np.all(np.isfinite(rates)):
            raise SetpointRejected(f"non-finite body rates {rates.tolist()}")
    else:
        quat = np.array([float(v) for v in q])
        norm = float(np.linalg.norm(quat))
        if not math.isfinite(norm) or norm < 0.5:
            raise SetpointRejected(f"attitude quaternion {quat.tolist()} is not a rotation")
        attitude = quat / norm
        rates = np.array([0.0, 0.0, rates[2] if math.isfinite(rates[2]) else 0.0])
    return Setpoint(time_s, thrust_norm, rates, attitude, int(type_mask))


class LandController(Protocol):
    """The autopilot's AUTO.LAND controller: ground truth in, Command out (the default is
    :class:`sitl_sim.autopilot.land_controller.CascadeLandController`)."""

    def command(self, pos_ned_m, vel_ned_m_s, quat_wxyz, v_down_m_s=None) -> Command: ...


@dataclass(frozen=True)
class AutopilotParams:
    """The PX4 parameters the SITL models (names and units as PX4's)."""

    com_of_loss_t_s: float = 1.0
    """COM_OF_LOSS_T: offboard setpoint silence that triggers the failsafe, s (sim time)."""
    com_obl_rc_act: int = COM_OBL_RC_ACT_LAND
    """COM_OBL_RC_ACT: action on offboard loss (4 = Land; the only one modelled)."""
    com_disarm_land_s: float = 2.0
    """COM_DISARM_LAND: auto-disarm this long after touchdown, s (sim time)."""
    mpc_thr_hover: float = 0.5
    """MPC_THR_HOVER: hover thrust, fraction of the maximum (read-only: from the vehicle)."""
    pld: PldParams = field(default_factory=PldParams)
    """PLD_*: the precision land (AUTO.PRECLAND)."""
    ltest: LteParams = field(default_factory=LteParams)
    """LTEST_*: the landing-target estimator."""
    ardu: ArduParams = field(default_factory=ArduParams)
    """ArduCopter's parameters (the ``ardupilot`` profile only; ``mpc_thr_hover`` is its
    MOT_THST_HOVER, ``pld`` its PLND_XY_DIST_MAX / PLND_TIMEOUT / PLND_RET_MAX)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.com_of_loss_t_s <= 60.0:
            raise ValueError(f"COM_OF_LOSS_T = {self.com_of_loss_t_s}; expected (0, 60] s")
        if self.com_obl_rc_act != COM_OBL_RC_ACT_LAND:
            raise ValueError(
                f"COM_OBL_RC_ACT = {self.com_obl_rc_act}; only {COM_OBL_RC_ACT_LAND} (Land) is "
                "modelled"
            )
        if not 0.0 <= self.com_disarm_land_s <= 20.0:
            raise ValueError(f"COM_DISARM_LAND = {self.com_disarm_land_s}; expected [0, 20] s")


@dataclass(frozen=True)
class AutopilotEvent:
    """Something the SITL must announce (STATUSTEXT, an immediate HEARTBEAT, the log).

    Attributes:
        kind: the ``/events`` kind it is logged as (``mode``, ``armed``, ``disarmed``,
            ``failsafe``, ``takeover``, ...).
        text: a human-readable line (the flight log's event; the STATUSTEXT).
        severity: MAV_SEVERITY (2 critical, 4 warning, 6 info).
        statustext: also sent as STATUSTEXT (False: the flight log only, e.g. an ArduCopter
            mode change, which ArduPilot shows in the HEARTBEAT alone).
    """

    kind: EventKind
    text: str
    severity: int = 6
    statustext: bool = True


class Autopilot:
    """Mode / arming / offboard state machine; feed it messages and sim time, read the command.

    This class is the ``px4`` profile; :class:`sitl_sim.autopilot.ardupilot.ArduCopter` overrides
    the
    hooks marked *profile hook* for the ``ardupilot`` one.

    Args:
        params: the PX4 parameters.
        armed: start armed (a vehicle hovering at its initial state is flying, hence armed).
    """

    profile = PX4.name
    hover_param = PX4.hover_param
    """The parameter that carries ``params.mpc_thr_hover`` on the wire."""
    precland_needs_range = True
    """AUTO.PRECLAND is refused without a distance to the ground (PX4 mode_requirements)."""
    runs_free_when_unanswered = False
    """In lockstep, after a frame's wait timed out in OFFBOARD, stop waiting until the client
    answers again (True where the mode never ends by itself on a dead client: ArduCopter's
    GUIDED_NOGPS; PX4 leaves OFFBOARD after COM_OF_LOSS_T)."""
    acks_set_mode = False
    """SET_MODE is answered with a COMMAND_ACK (command 11): ArduPilot does, PX4 does not."""
    _armed_text = "Armed"

    def __init__(self, params: AutopilotParams, *, armed: bool = True) -> None:
        self.params = params
        self.mode = FlightMode.HOLD
        self.armed = armed
        self.taken_over = False
        """Physics has started this episode (armed in a mode other than HOLD at least once)."""
        self.setpoint: Setpoint | None = None
        self._landed_since_s: float | None = None
        self._events: list[AutopilotEvent] = []

    # ------------------------------------------------------------------ queries

    @property
    def physics_running(self) -> bool:
        """Physics integrates (False: the vehicle is frozen, HOLD or not yet taken over)."""
        return self.taken_over and self.mode is not FlightMode.HOLD

    def setpoint_fresh(self, now_s: float) -> bool:
        sp = self.setpoint
        return sp is not None and now_s - sp.time_s <= self.params.com_of_loss_t_s

    def pop_events(self) -> list[AutopilotEvent]:
        events, self._events = self._events, []
        return events

    # ------------------------------------------------------------------ profile hooks

    @property
    def mode_label(self) -> str:
        """The mode's name as this autopilot calls it (logs, events)."""
        return self.mode.label

    def heartbeat(self) -> tuple[int, int, int, int]:
        """HEARTBEAT ``(autopilot, base_mode, custom_mode, system_status)`` (type QUADROTOR)."""
        return (
            PX4.mav_autopilot,
            base_mode(self.mode, self.armed),
            custom_mode(self.mode),
            _MAV_STATE_ACTIVE if self.armed else _MAV_STATE_STANDBY,
        )

    def mode_for_command(self, param2: float, param3: float) -> FlightMode | bool | None:
        """The mode a DO_SET_MODE (custom flag set) asks for: PX4 main mode, sub mode."""
        return mode_from_custom(int(param2), int(param3))

    def mode_for_custom(self, custom: int) -> FlightMode | bool | None:
        """The mode a SET_MODE ``custom_mode`` asks for."""
        return mode_from_custom((custom >> 16) & 0xFF, (custom >> 24) & 0xFF)

    def land_mode(self) -> FlightMode:
        """What MAV_CMD_NAV_LAND selects."""
        return FlightMode.LAND

    def setpoint_from_message(self, *target: Any) -> Setpoint | None:
        """A SET_ATTITUDE_TARGET read as this autopilot reads it (None: silently ignored):
        ``target`` is :func:`setpoint_from_target`'s arguments but the last, the thrust kept
        from the previous setpoint, which this autopilot holds (``type_mask``, ``q``,
        ``body_rates``, ``thrust``, ``thrust_body``, ``time_s``).

        Raises:
            SetpointRejected: see :func:`setpoint_from_target`.
        """
        prev = self.setpoint
        return setpoint_from_target(*target, prev.thrust_norm if prev is not None else None)

    def flight_command(self, now_s: float, truth) -> Command | None:
        """This autopilot's own command for the physics step, or None for the SITL's
        (OFFBOARD setpoint, AUTO.LAND / AUTO.PRECLAND controllers). ``truth()`` gives the
        ground truth, read only when needed."""
        return None

    def on_heartbeat(self, sysid: int, compid: int, now_s: float) -> None:
        """A HEARTBEAT from another system or component (PX4 here: nothing to do)."""

    def check_landing_target(self, frame: int, position_valid: int, distance: float) -> None:
        """Refuse a LANDING_TARGET this autopilot drops before reading it (PX4: none here;
        :func:`sitl_sim.autopilot.precland.measurement_from_landing_target` does PX4's checks)."""

    # ------------------------------------------------------------------ inputs

    def on_setpoint(self, setpoint: Setpoint) -> None:
        """An accepted SET_ATTITUDE_TARGET: the proof of life of the offboard link."""
        self.setpoint = setpoint

    def request_mode(self, mode: FlightMode | bool | None, now_s: float) -> MavResult:
        """DO_SET_MODE / SET_MODE / NAV_LAND. OFFBOARD needs a fresh setpoint stream."""
        if mode is None:
            return MavResult.DENIED
        if mode is False:
            return MavResult.TEMPORARILY_REJECTED
        assert isinstance(mode, FlightMode)
        if mode is FlightMode.OFFBOARD and not self.setpoint_fresh(now_s):
            return MavResult.TEMPORARILY_REJECTED
        self._set_mode(mode, f"mode {mode.label}")
        self._maybe_take_over()
        return MavResult.ACCEPTED

    def request_arm(self, arm: bool, *, force: bool, in_air: bool) -> MavResult:
        """ARM_DISARM. Disarming in the air needs ``force`` (param2 = 21196), as in PX4."""
        if arm:
            if not self.armed:
                self.armed = True
                self._events.append(AutopilotEvent(EventKind.ARMED, self._armed_text, 6))
                self._maybe_take_over()
            return MavResult.ACCEPTED
        if self.armed and in_air and not force:
            return MavResult.DENIED
        if self.armed:
            self._disarm("Disarmed by command")
        return MavResult.ACCEPTED

    def update(self, now_s: float, *, on_ground: bool) -> None:
        """Periodic checks (PX4 runs them at 10 Hz; the SITL calls this every control period)."""
        if self.mode is FlightMode.OFFBOARD and not self.setpoint_fresh(now_s):
            self._set_mode(
                FlightMode.LAND,
                f"Failsafe: offboard setpoints lost > {self.params.com_of_loss_t_s:.1f} s, landing",
                severity=2,
                kind=EventKind.FAILSAFE,
            )
        if self.armed and self.physics_running and on_ground:
            if self._landed_since_s is None:
                self._landed_since_s = now_s
            elif now_s - self._landed_since_s >= self.params.com_disarm_land_s - 1e-9:
                self._disarm(f"Landed: auto-disarm after {self.params.com_disarm_land_s:.1f} s")
        else:
            self._landed_since_s = None

    # ------------------------------------------------------------------ internals

    def _set_mode(
        self, mode: FlightMode, text: str, severity: int = 6, kind: EventKind = EventKind.MODE
    ) -> None:
        if mode is not self.mode:
            self.mode = mode
            self._events.append(AutopilotEvent(kind, text, severity))

    def _disarm(self, text: str) -> None:
        self.armed = False
        self._landed_since_s = None
        self._events.append(AutopilotEvent(EventKind.DISARMED, text, 6))

    def _maybe_take_over(self) -> None:
        if not self.taken_over and self.armed and self.mode is not FlightMode.HOLD:
            self.taken_over = True
            self._events.append(
                AutopilotEvent(EventKind.TAKEOVER, f"Flight starts in {self.mode_label}")
            )
