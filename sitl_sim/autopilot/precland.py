"""PX4-like precision landing on LANDING_TARGET: the message's reading, the landing-target
estimator and the navigator's precision-land state machine. No I/O, sim time in, no ground truth:
everything runs in the frame of the autopilot's own estimate
(:class:`~sitl_sim.autopilot.nav_estimator.NavEstimator`).

Sources (paraphrased in ``shared/reference/precland_notes.md``): PX4 ``mavlink_receiver.cpp``
``handle_message_landing_target`` (2.1), ``landing_target_estimator`` (2.3) and
``navigator/precland.cpp`` (2.5, 2.6).

**LANDING_TARGET** (:func:`measurement_from_landing_target`), three forms:

* ``position_valid = 0`` — the *angle* form, PX4's IR-LOCK path: ``angle_x``/``angle_y`` are
  used as the tangents of the target's offset (PX4 copies them into ``irlock_report.pos_x/y``
  without ``tan()``), camera x = body right, camera y = body backward (``LTEST_SENS_ROT`` = yaw
  90°); the frame field, ``distance`` and ``time_usec`` are ignored (receive time is used), the
  scale comes from the range finder (PX4 refuses without ``dist_bottom``).
* ``position_valid = 1``, ``MAV_FRAME_LOCAL_NED`` — PX4's absolute form: x, y, z is the target in
  the autopilot's local frame.
* ``position_valid = 1``, ``MAV_FRAME_BODY_FRD`` — ArduPilot's position form (x, y, z = the
  target in body FRD, ``distance`` = its norm). **A real PX4 drops it** ("coordinate frame 12
  unsupported"); this SITL accepts it (checklist item 9, ArduPilot compatibility) and uses
  x, y, z rotated by the attitude estimate.

Anything else — another frame with a position, ``position_valid`` not 0/1, a non-finite field —
raises :class:`LandingTargetRejected` (the SITL counts it and flies on; an unsupported frame is
also a CRITICAL STATUSTEXT as in PX4).

**Landing-target estimator** (:class:`LandingTargetEstimator`, PX4's LTE): per horizontal axis a
Kalman filter of the target's position and velocity *relative to the vehicle* (target minus
vehicle, NED), predicted with minus the vehicle's acceleration, measurement variance
``LTEST_MEAS_UNC · height²``, a 3.84 (χ², 1 dof, 5 %) innovation gate on each axis (both must
pass), reset after 2 s without an accepted measurement. Its absolute target is relative +
the vehicle's estimated position.

**Precision land** (:class:`PrecisionLand`, AUTO.PRECLAND = "required"): START → (target seen)
HORIZONTAL_APPROACH (altitude held) → (within ``PLD_HACC_RAD`` on each axis, fresh, for 2 s)
DESCEND_ABOVE_TARGET → (below ``PLD_FAPPR_ALT`` with the target older than 0.5 s)
FINAL_APPROACH; a target lost for ``PLD_BTOUT`` above that → START again (→ SEARCH at
``PLD_SRCH_ALT`` for at most ``PLD_SRCH_TOUT``) while fewer than ``PLD_MAX_SRCH`` searches were
made, else FALLBACK: a normal landing where the target was last seen, on the estimate.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from companion.table import Bounded, bounded
from sitl_sim.autopilot.nav_estimator import NavEstimator, rotation_from_euler

__all__ = [
    "LTE_TIMEOUT_S",
    "LandingTargetEstimator",
    "LandingTargetRejected",
    "LteParams",
    "Measurement",
    "PldParams",
    "PrecisionLand",
    "PreclandEvent",
    "PreclandSetpoint",
    "PreclandState",
    "measurement_from_landing_target",
]

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12

LTE_TIMEOUT_S = 2.0
"""PX4 landing_target_estimator_TIMEOUT_US: no accepted update this long → the filter resets."""
_NIS_GATE = 3.84
"""χ² 1 dof 5 %: PX4 LTE's innovation gate per axis."""
_FRESH_FOR_DESCENT_S = 1.0
"""HORIZONTAL_APPROACH → DESCEND needs a target this fresh (PX4: a new pose this cycle)."""
_FINAL_APPROACH_STALE_S = 0.5
"""Near the ground a pose older than this counts as lost (PX4 precland.cpp)."""
_SETTLE_S = 2.0
"""Inside the acceptance radius this long before descending (PX4 precland.cpp)."""
_START_POINT_S = 1.0
"""At the approximate landing point this long before searching (PX4 precland.cpp)."""
_APPROX_POINT_RADIUS_M = 2.0
"""'At the approximate landing point' (PX4 uses the navigator's acceptance radius)."""
_SEARCH_SEEN_S = 1.0
"""Target seen during SEARCH this long → HORIZONTAL_APPROACH."""


class LandingTargetRejected(ValueError):
    """A LANDING_TARGET this autopilot ignores; ``unsupported_frame`` names PX4's one loud case."""

    def __init__(self, text: str, unsupported_frame: int | None = None) -> None:
        super().__init__(text)
        self.unsupported_frame = unsupported_frame


@dataclass(frozen=True)
class Measurement:
    """One accepted LANDING_TARGET, as the estimator takes it.

    Attributes:
        kind: ``angles`` (tan-angle ray in the camera frame), ``body`` (target in body FRD, m)
            or ``local`` (target in the local NED frame, m).
        vector: (3,) the ray (tan_x, tan_y, 1) for ``angles``, else the position.
        time_s: receive time (sim).
    """

    kind: str
    vector: np.ndarray
    time_s: float


def measurement_from_landing_target(
    frame: int,
    angle_x: float,
    angle_y: float,
    distance: float,
    x: float,
    y: float,
    z: float,
    position_valid: int,
    time_s: float,
) -> Measurement:
    """Read a LANDING_TARGET's fields as PX4's receiver does (module docstring).

    Raises:
        LandingTargetRejected: a form this autopilot ignores, or a non-finite value.
    """
    if position_valid not in (0, 1):
        raise LandingTargetRejected(f"position_valid = {position_valid}; MAV_BOOL is 0 or 1")
    if position_valid == 0:
        if not (math.isfinite(angle_x) and math.isfinite(angle_y)):
            raise LandingTargetRejected(f"non-finite angles ({angle_x}, {angle_y})")
        return Measurement("angles", np.array([angle_x, angle_y, 1.0]), time_s)
    pos = np.array([x, y, z], dtype=float)
    if not np.all(np.isfinite(pos)):
        raise LandingTargetRejected(f"non-finite position {pos.tolist()}")
    if frame == MAV_FRAME_LOCAL_NED:
        return Measurement("local", pos, time_s)
    if frame == MAV_FRAME_BODY_FRD:
        if not pos[2] > 0:
            raise LandingTargetRejected(f"body FRD target {pos.tolist()} is not below the vehicle")
        return Measurement("body", pos, time_s)
    raise LandingTargetRejected(
        f"Landing target: coordinate frame {frame} unsupported", unsupported_frame=frame
    )


@dataclass(frozen=True)
class LteParams(Bounded):
    """PX4 ``LTEST_*`` (landing_target_estimator module.yaml defaults).

    ``mode`` 1 (Stationary) is *not* PX4's default (0, Moving): without GPS the vehicle's own
    velocity drifts, and a static target's relative velocity is the only velocity aiding there
    is (PX4 fuses it into the EKF in Stationary mode). A target that moves (a rover, a deck)
    needs 0 (Moving): the target is then used for setpoints only, re-published every cycle
    from the filter's prediction, and the precision land feeds its velocity forward
    (:attr:`PreclandSetpoint.velocity_ne_m_s`), as ArduPilot's ``PLND_OPTIONS`` bit 0 and
    PX4's newer ``PLD_MOVING_T`` do: the position loop then flies the relative state alone, and
    the vehicle's own velocity error cancels out of it.
    """

    mode: int = 1
    acc_unc: float = bounded(10.0, 0.0, lo_open=True, name="LTEST_ACC_UNC")
    meas_unc: float = bounded(0.005, 0.0, lo_open=True, name="LTEST_MEAS_UNC")
    pos_unc_in: float = bounded(0.1, 0.0, lo_open=True, name="LTEST_POS_UNC_IN")
    vel_unc_in: float = bounded(0.1, 0.0, lo_open=True, name="LTEST_VEL_UNC_IN")

    def __post_init__(self) -> None:
        if self.mode not in (0, 1):
            raise ValueError(f"LTEST_MODE = {self.mode}; expected 0 (Moving) or 1 (Stationary)")
        super().__post_init__()


@dataclass(frozen=True)
class PldParams(Bounded):
    """PX4 ``PLD_*`` (navigator precland_params.c defaults and ranges)."""

    btout_s: float = bounded(5.0, 0.0, 50.0, name="PLD_BTOUT")
    hacc_rad_m: float = bounded(1.0, 0.0, 100.0, name="PLD_HACC_RAD")
    """Not PX4's 0.2 m: a camera estimate of a pad 75-100 m below wanders by ±0.3-0.5 m, and
    with 0.2 m per axis held for 2 s one nominal episode in six hovered in HORIZONTAL_APPROACH
    until its 90 s timeout with the vehicle 2 cm from the pad (PX4 issue #25096; PX4's own VTE
    guide says to raise it, "try 2 m"). The descent tracks the target all the way down, so the
    landing accuracy does not depend on it."""
    fappr_alt_m: float = bounded(0.1, 0.0, 10.0, name="PLD_FAPPR_ALT")
    srch_alt_m: float = bounded(10.0, 0.0, 100.0, name="PLD_SRCH_ALT")
    srch_tout_s: float = bounded(10.0, 0.0, 100.0, name="PLD_SRCH_TOUT")
    max_srch: int = bounded(3, 0, 100, name="PLD_MAX_SRCH")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.max_srch != int(self.max_srch):
            raise ValueError(f"PLD_MAX_SRCH = {self.max_srch}; expected an integer")


class LandingTargetEstimator:
    """Target position and velocity relative to the vehicle (target − vehicle), north and east.

    Args:
        params: the LTEST_* parameters.
    """

    def __init__(self, params: LteParams) -> None:
        self.params = params
        self.x = np.zeros((2, 2))
        """(2, 2): per axis N, E (relative position m, relative velocity m/s)."""
        self.cov = np.zeros((2, 2, 2))
        self.initialised = False
        self.last_update_s = -math.inf
        """Sim time of the last accepted measurement."""
        self.height_m = math.nan
        """Height above the target at the last accepted measurement (PX4 ``z_rel``)."""
        self.abs_ne_m = np.full(2, math.nan)
        """The target in the estimate frame as last published (PX4 ``x_abs``, ``y_abs``): the
        relative position + the vehicle's estimated position at the last accepted measurement.
        Nothing is published while the target is unseen, so it stays where it was seen (in
        Stationary mode; Moving: :meth:`publish`)."""
        self.abs_vel_ne_m_s = np.zeros(2)
        """Moving mode: the target's velocity as last published (estimate frame)."""
        self.accepted = 0
        self.rejected = 0

    @property
    def moving(self) -> bool:
        """``LTEST_MODE`` 0: the target may move (module docstring of :class:`LteParams`)."""
        return self.params.mode == 0

    def publish(self, nav: NavEstimator, dt_s: float) -> None:
        """Moving mode: re-publish the target every cycle — from the filter's prediction
        (relative + the vehicle's estimated position) while it runs, and after it reset, moved
        on at its last velocity (the pose's age still counts from the last measurement, so
        PLD_BTOUT still ends it). Stationary keeps the last measured one."""
        if not self.moving or not math.isfinite(self.last_update_s):
            return
        if self.initialised:
            self.abs_ne_m = nav.pos_ned_m[:2] + self.x[:, 0]
            self.abs_vel_ne_m_s = self.target_vel_ne(nav)
        else:
            self.abs_ne_m = self.abs_ne_m + self.abs_vel_ne_m_s * dt_s

    def target_vel_ne(self, nav: NavEstimator) -> np.ndarray:
        """The target's velocity in the estimate frame: relative + the vehicle's own."""
        return self.x[:, 1] + nav.vel_ned_m_s[:2]

    def predict(self, dt_s: float, vehicle_accel_ned_m_s2: np.ndarray, now_s: float) -> None:
        if not self.initialised:
            return
        if now_s - self.last_update_s > LTE_TIMEOUT_S:
            self.initialised = False  # PX4: re-initialise from the next measurement
            return
        a = -np.asarray(vehicle_accel_ned_m_s2[:2], dtype=float)
        fm = np.array([[1.0, dt_s], [0.0, 1.0]])
        q = self.params.acc_unc * np.array([[dt_s**4 / 4, dt_s**3 / 2], [dt_s**3 / 2, dt_s**2]])
        self.x[:, 0] += self.x[:, 1] * dt_s + 0.5 * a * dt_s * dt_s
        self.x[:, 1] += a * dt_s
        for axis in range(2):
            self.cov[axis] = fm @ self.cov[axis] @ fm.T + q

    def relative_from(self, meas: Measurement, nav: NavEstimator) -> np.ndarray | None:
        """The measured relative position (N, E, D), or None when the geometry fails (no height
        for an angle ray, a ray not pointing down)."""
        if meas.kind == "local":
            return meas.vector - nav.pos_ned_m
        rot = rotation_from_euler(nav.attitude_rad)
        if meas.kind == "body":
            return rot @ meas.vector
        # PX4 LTE: sensor (x, y, 1) rotated by LTEST_SENS_ROT (yaw 90°) → body (-y, x, 1)
        tan_x, tan_y = float(meas.vector[0]), float(meas.vector[1])
        ray = rot @ np.array([-tan_y, tan_x, 1.0])
        height = nav.altitude_m
        if abs(ray[2]) < 1e-6 or ray[2] < 0 or not (math.isfinite(height) and height > 0):
            return None
        return np.array([ray[0] / ray[2] * height, ray[1] / ray[2] * height, height])

    def update(self, meas: Measurement, nav: NavEstimator) -> bool:
        """Fuse one measurement; returns whether it was accepted."""
        rel = self.relative_from(meas, nav)
        if rel is None or not np.all(np.isfinite(rel)):
            self.rejected += 1
            return False
        height = max(float(rel[2]), 0.1)
        r = self.params.meas_unc * height * height
        if not self.initialised:
            self.x[:, 0] = rel[:2]
            self.x[:, 1] = -nav.vel_ned_m_s[:2]
            self.cov[:] = np.diag([self.params.pos_unc_in, self.params.vel_unc_in])
            self.initialised = True
        else:
            innov = rel[:2] - self.x[:, 0]
            s = self.cov[:, 0, 0] + r
            if np.any(innov * innov / s > _NIS_GATE):
                self.rejected += 1
                return False
            for axis in range(2):
                p = self.cov[axis]
                k = p[:, 0] / s[axis]
                self.x[axis] += k * innov[axis]
                self.cov[axis] = p - np.outer(k, p[0, :])
        self.last_update_s = meas.time_s
        self.height_m = float(rel[2])
        self.abs_ne_m = nav.pos_ned_m[:2] + self.x[:, 0]
        self.accepted += 1
        return True

    def age_s(self, now_s: float) -> float:
        """Time since the last published target (inf: never). A filter reset (2 s without a
        measurement) does not withdraw the pose: PX4's navigator judges its age by PLD_BTOUT."""
        return now_s - self.last_update_s


class PreclandState(enum.Enum):
    """PX4 navigator ``PrecLandState``."""

    START = "start"
    HORIZONTAL_APPROACH = "horizontal_approach"
    DESCEND_ABOVE_TARGET = "descend_above_target"
    FINAL_APPROACH = "final_approach"
    SEARCH = "search"
    FALLBACK = "fallback"


@dataclass(frozen=True)
class PreclandSetpoint:
    """What the position controller flies: a horizontal point in the estimate frame, and
    either a held altitude or (``altitude_m`` None) the land descent."""

    north_east_m: np.ndarray
    altitude_m: float | None
    velocity_ne_m_s: np.ndarray | None = None
    """A moving target's velocity, fed forward (``LTEST_MODE`` 0 while it is tracked); None:
    a still point."""


@dataclass(frozen=True)
class PreclandEvent:
    """A state change to announce (STATUSTEXT + flight log), PX4's wording where it has one."""

    state: PreclandState
    text: str
    severity: int = 6


class PrecisionLand:
    """The navigator's precision land, ``required`` (AUTO.PRECLAND), on the estimate.

    Args:
        params: PLD_* parameters.
        nav: the autopilot's estimate (read only).
        lte: the landing-target estimator (read only).
        now_s: activation time.
    """

    def __init__(
        self, params: PldParams, nav: NavEstimator, lte: LandingTargetEstimator, now_s: float
    ) -> None:
        self.params = params
        self.nav = nav
        self.lte = lte
        self.state = PreclandState.START
        self.search_count = 0
        self.approx_ne_m = nav.pos_ned_m[:2]
        """Where to land without a target: the activation point, then the last target seen."""
        self._hold_alt_m = nav.altitude_m
        self._entered_s = now_s
        self._timer_s: float | None = None
        self.events: list[PreclandEvent] = [
            PreclandEvent(PreclandState.START, "Precision landing: started (required)")
        ]

    # ------------------------------------------------------------------ queries

    def target_ne_m(self) -> np.ndarray:
        """The target's horizontal position in the estimate frame (PX4 ``x_abs``, ``y_abs``)."""
        return self.lte.abs_ne_m.copy()

    def _valid(self, now_s: float) -> bool:
        return self.lte.age_s(now_s) <= self.params.btout_s

    def pop_events(self) -> list[PreclandEvent]:
        events, self.events = self.events, []
        return events

    # ------------------------------------------------------------------ the state machine

    def _switch(self, state: PreclandState, now_s: float, text: str, severity: int = 6) -> None:
        self.state = state
        self._entered_s = now_s
        self._timer_s = None
        self._hold_alt_m = self.nav.altitude_m
        self.events.append(PreclandEvent(state, text, severity))

    def _lost(self, now_s: float, where: str) -> None:
        """Target lost above the final approach: search again, or land without it."""
        if self.search_count < self.params.max_srch and self.params.srch_tout_s > 0:
            self._switch(
                PreclandState.START, now_s, f"Precision landing: target lost {where}, searching", 4
            )
        else:
            self._fallback(now_s, f"target lost {where}")

    def _fallback(self, now_s: float, why: str) -> None:
        self._switch(
            PreclandState.FALLBACK, now_s, f"Precision landing: {why}, landing normally", 4
        )

    def _held_for(self, holds: bool, now_s: float, dwell_s: float) -> bool:
        """Whether the state's condition, ``holds`` this cycle, has held longer than
        ``dwell_s``: its first cycle starts the timer (``_timer_s``), a cycle without it
        clears the timer."""
        if not holds:
            self._timer_s = None
            return False
        self._timer_s = now_s if self._timer_s is None else self._timer_s
        return now_s - self._timer_s > dwell_s

    def update(self, now_s: float) -> PreclandSetpoint:
        """One navigator cycle (the SITL runs it at its 10 Hz control rate)."""
        p, nav = self.params, self.nav
        valid = self._valid(now_s)
        if valid and self.state not in (PreclandState.FALLBACK, PreclandState.FINAL_APPROACH):
            # PX4 overwrites the approximate landing point with the latest target position
            self.approx_ne_m = self.target_ne_m()
        state = self.state
        if state is PreclandState.START:
            if valid:
                self._switch(
                    PreclandState.HORIZONTAL_APPROACH, now_s, "Precision landing: target acquired"
                )
            elif self._held_for(
                np.linalg.norm(nav.pos_ned_m[:2] - self.approx_ne_m) < _APPROX_POINT_RADIUS_M,
                now_s,
                _START_POINT_S,
            ):
                if p.srch_tout_s > 0 and self.search_count < p.max_srch:
                    self.search_count += 1
                    self._switch(
                        PreclandState.SEARCH,
                        now_s,
                        f"Precision landing: climbing to search altitude ({self.search_count})",
                    )
                else:
                    self._fallback(now_s, "no target")
        elif state is PreclandState.HORIZONTAL_APPROACH:
            if not valid:
                self._lost(now_s, "in approach")
            else:
                err = np.abs(nav.pos_ned_m[:2] - self.target_ne_m())
                over = self.lte.age_s(now_s) <= _FRESH_FOR_DESCENT_S and bool(
                    np.all(err < p.hacc_rad_m)
                )
                if self._held_for(over, now_s, _SETTLE_S):
                    self._switch(
                        PreclandState.DESCEND_ABOVE_TARGET,
                        now_s,
                        "Precision landing: over the target, descending",
                    )
        elif state is PreclandState.DESCEND_ABOVE_TARGET:
            near = nav.altitude_m < p.fappr_alt_m
            if near and self.lte.age_s(now_s) > _FINAL_APPROACH_STALE_S:
                self._switch(
                    PreclandState.FINAL_APPROACH, now_s, "Precision landing: final approach"
                )
            elif not valid:
                self._lost(now_s, "in descent")
        elif state is PreclandState.SEARCH:
            if self._held_for(valid, now_s, _SEARCH_SEEN_S):
                self._switch(
                    PreclandState.HORIZONTAL_APPROACH,
                    now_s,
                    "Precision landing: target found in search",
                )
            elif not valid and now_s - self._entered_s > p.srch_tout_s:
                self._fallback(now_s, "search timed out")
        return self._setpoint(now_s)

    def _setpoint(self, now_s: float) -> PreclandSetpoint:
        state = self.state
        follow = None
        moving = self.lte.moving and math.isfinite(self.lte.last_update_s)
        if state in (PreclandState.HORIZONTAL_APPROACH, PreclandState.DESCEND_ABOVE_TARGET) or (
            moving and state is PreclandState.FINAL_APPROACH
        ):
            # a moving target is followed down to the ground on its prediction
            ne = self.target_ne_m()
            if moving:
                follow = self.lte.abs_vel_ne_m_s.copy()
        else:
            ne = self.approx_ne_m.copy()
        if state is PreclandState.SEARCH:
            # climb (or descend) to the search altitude; seeing the target stops it (PX4: +1 m)
            seen = self._timer_s is not None
            alt = self._hold_alt_m if seen else self.params.srch_alt_m
            if seen:
                alt = self._hold_alt_m = min(self.nav.altitude_m + 1.0, self._hold_alt_m)
            return PreclandSetpoint(ne, alt)
        if state in (PreclandState.START, PreclandState.HORIZONTAL_APPROACH):
            return PreclandSetpoint(ne, self._hold_alt_m, follow)
        return PreclandSetpoint(ne, None, follow)  # descend, final approach, fallback: land
