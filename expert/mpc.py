"""The MPC expert (paper section 3.2): a linear MPC on privileged state, solved with OSQP.

Model. State ``x`` (9, :class:`ModelState`): position NED (m), velocity NED (m/s), roll/pitch/yaw
(rad, ZYX). Input ``u`` (4, :class:`ModelInput`): ``thrust_norm`` and FRD body rates (rad/s) —
exactly the :class:`~companion.contract.Command` space, so expert labels are what the companion
sends. ``f(x, u)`` is evaluated through ``sitl_sim.dynamics.derivative`` (gravity, collective
thrust, body drag and quaternion kinematics), so no physics constant is retyped here; the
Jacobians about hover are central differences of it, discretised by zero-order hold
(``scipy.linalg.expm``) at the control period. Two cheap corrections keep the hover model honest
away from hover, both computed per solve from the same physics:

* the residual ``f(x0, u_hover) - A x0`` at the current state (mostly body drag, quadratic and
  so invisible to a hover linearisation) is fed forward as a constant affine term;
* the rate loop follows a setpoint with a lag (``1/kp`` + rotor lag, from the vehicle config)
  the model does not have, so the start attitude is led by the rotation still under way.

Yaw. The model is linearised at yaw 0; every solve works in the *heading frame*: horizontal
position and velocity rotated by ``-yaw`` so the current yaw is 0 in the model. The heading held
is the one of the episode's first step (kept in the policy state, :class:`MpcState`); its error
is a state the MPC drives to zero with ``r``, and the rate loop damps any yaw rate.

QP (OSQP, sparse, built once). Variables ``z = [x_1..x_N, du_0..du_{N-1}, s_1..s_N]``, with
``du = u - u_hover`` and ``s_k >= 0`` one slack per step for the soft constraints. Cost: control
effort about hover; tracking of a descent-speed profile that slows down near the ground; and, as
the paper's proximity switch, two cost sets: *far* (efficiency first, the pad only as a terminal
cost) and *near* (a position-tracking cost at every step). Each cost set has its own OSQP
instance, set up once; per step only the vectors ``q``, ``l``, ``u`` change. Constraints:

* dynamics;
* ``0 <= thrust <= max_thrust_mg * m g``, body rates within the autopilot's ``max_rate_rad_s``;
* ``|roll|, |pitch| <= max_tilt_deg`` (hard; from a state already beyond it, a funnel back to it
  that the rate limits can follow, so the QP is feasible from any attitude);
* soft, with an exact (linear + quadratic) slack penalty so they hold whenever they can and a
  state a learner drove too low or too fast still gets a best-effort label: altitude
  ``>= -ground_margin_m`` (paper: ``z >= 0``; touchdown is an event the plan flies through, not
  a state it must stop at) and downward speed ``<= at_ground + slope * altitude`` (what makes
  the touchdown soft).

A solve whose status is not *solved* is never used: the same QP goes to Clarabel (interior
point, direct API), and if that fails too :class:`MpcSolveError` is raised for the caller to
record. Counts are in :attr:`MpcExpert.stats`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields
from enum import IntEnum
from pathlib import Path
from typing import Any

import clarabel
import numpy as np
import osqp
import scipy.sparse as sp
from scipy.linalg import expm

from companion.contract import Command, Observation
from companion.contract import MissingGroundTruthError, PolicyError
from sitl_sim.config import CONFIG_DIR, SimConfig, VehicleConfig, load_toml
from sitl_sim.dynamics import (
    Physics,
    derivative,
    euler_from_quat,
    make_state,
    quat_from_euler,
    translational_accel_ned,
)
from sitl_sim.errors import ConfigError
from companion.contract import GroundTruth

__all__ = [
    "HoverModel",
    "ModelInput",
    "ModelState",
    "MpcConfig",
    "MpcExpert",
    "MpcPlan",
    "MpcSolveError",
    "MpcState",
    "MpcStats",
    "linearise_hover",
    "load_mpc_config",
    "model_derivative",
]


# --------------------------------------------------------------------------- configuration


def _param(table: str, lo: float, hi: float, unit: str, doc: str, *, integer: bool = False) -> Any:
    """A config field: its TOML table, inclusive range, unit and help text (PX4 module.yaml)."""
    return field(
        metadata={"table": table, "lo": lo, "hi": hi, "unit": unit, "doc": doc, "int": integer}
    )


@dataclass(frozen=True)
class MpcConfig:
    """Tuning of the MPC expert, read from ``configs/expert.toml`` (every key required).

    Each field's metadata holds its TOML table, range, unit and help text; values are checked
    on construction, so a config built in code is validated the same way as one read from disk.
    """

    horizon_steps: int = _param("mpc", 5, 200, "steps", "prediction horizon", integer=True)
    near_distance_m: float = _param(
        "mpc", 0.0, 1e3, "m", "distance to the pad below which the near (tracking) cost is used"
    )
    max_descent_m_s: float = _param("descent", 0.05, 20.0, "m/s", "fastest reference descent")
    touchdown_descent_m_s: float = _param(
        "descent", 0.0, 2.0, "m/s", "reference descent speed at the ground"
    )
    descent_gain_1_s: float = _param(
        "descent", 0.0, 10.0, "1/s", "reference descent speed per metre of altitude"
    )
    descent_limit_at_ground_m_s: float = _param(
        "descent", 0.0, 5.0, "m/s", "soft limit on downward speed at the ground"
    )
    descent_limit_slope_1_s: float = _param(
        "descent", 0.0, 10.0, "1/s", "growth of that limit per metre of altitude"
    )
    approach_slope: float = _param(
        "descent", 0.0, 100.0, "m/m", "approach cone: altitude kept per metre off the pad"
    )
    approach_deadband_m: float = _param(
        "descent", 0.0, 100.0, "m", "horizontal distance within which the cone does not apply"
    )
    max_thrust_mg: float = _param("limits", 1.0, 10.0, "m g", "collective thrust limit")
    max_tilt_deg: float = _param("limits", 1.0, 80.0, "deg", "roll and pitch limit")
    ground_margin_m: float = _param(
        "limits", 0.0, 1.0, "m", "predicted altitude may go this far below 0"
    )
    far_pos_ne: float = _param("weights", 0.0, 1e6, "1/m^2", "far: horizontal position")
    far_vel_ne: float = _param("weights", 0.0, 1e6, "s^2/m^2", "far: horizontal velocity")
    near_pos_ne: float = _param("weights", 0.0, 1e6, "1/m^2", "near: horizontal position")
    near_vel_ne: float = _param("weights", 0.0, 1e6, "s^2/m^2", "near: horizontal velocity")
    pos_d: float = _param("weights", 0.0, 1e6, "1/m^2", "altitude vs the descent profile")
    vel_d: float = _param("weights", 0.0, 1e6, "s^2/m^2", "downward speed vs the profile")
    tilt: float = _param("weights", 0.0, 1e6, "1/rad^2", "roll and pitch")
    yaw: float = _param("weights", 0.0, 1e6, "1/rad^2", "yaw error from the held heading")
    terminal_pos_ne: float = _param(
        "weights", 0.0, 1e6, "1/m^2", "terminal horizontal position (added at step N)"
    )
    terminal_vel_ne: float = _param(
        "weights", 0.0, 1e6, "s^2/m^2", "terminal horizontal velocity (added at step N)"
    )
    thrust_norm: float = _param("weights", 1e-6, 1e6, "1", "thrust_norm about hover")
    rate_roll_pitch: float = _param("weights", 1e-6, 1e6, "s^2/rad^2", "roll and pitch rates")
    rate_yaw: float = _param("weights", 1e-6, 1e6, "s^2/rad^2", "yaw rate")
    slack_linear: float = _param("weights", 0.0, 1e9, "1/unit", "safety slack, linear (exact)")
    slack_quadratic: float = _param("weights", 0.0, 1e9, "1/unit^2", "safety slack, quadratic")
    osqp_eps_abs: float = _param("solver", 1e-9, 1e-1, "1", "OSQP absolute tolerance")
    osqp_eps_rel: float = _param("solver", 1e-9, 1e-1, "1", "OSQP relative tolerance")
    osqp_max_iter: int = _param("solver", 1, 1_000_000, "1", "OSQP iterations", integer=True)
    clarabel_max_iter: int = _param(
        "solver", 1, 10_000, "1", "Clarabel (fallback) iterations", integer=True
    )

    def __post_init__(self) -> None:
        _check_config(self, "MpcConfig")

    def to_dict(self) -> dict[str, Any]:
        """The effective config, as saved with every artifact."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _check_value(value: Any, meta: dict[str, Any], where: str) -> float | int:
    kind = "an integer" if meta["int"] else "a number"
    ok_type = isinstance(value, int) if meta["int"] else isinstance(value, int | float)
    if isinstance(value, bool) or not ok_type:
        raise ConfigError(f"{where} must be {kind} ({meta['unit']}), got {value!r}")
    if not math.isfinite(value) or not meta["lo"] <= value <= meta["hi"]:
        raise ConfigError(
            f"{where} = {value} is out of range; expected [{meta['lo']}, {meta['hi']}] "
            f"({meta['unit']}: {meta['doc']})"
        )
    return int(value) if meta["int"] else float(value)


def _check_config(cfg: MpcConfig, source: str) -> None:
    for f in fields(cfg):
        _check_value(getattr(cfg, f.name), dict(f.metadata), f"{source}: {f.name}")
    if cfg.touchdown_descent_m_s > cfg.max_descent_m_s:
        raise ConfigError(
            f"{source}: touchdown_descent_m_s = {cfg.touchdown_descent_m_s} exceeds "
            f"max_descent_m_s = {cfg.max_descent_m_s}; expected touchdown <= max"
        )


def load_mpc_config(path: str | Path | None = None) -> MpcConfig:
    """Load and validate ``configs/expert.toml`` (or ``path``).

    Raises:
        ConfigError: naming the file, the table and the field that is missing, unknown,
            mistyped or out of range.
    """
    path = Path(path) if path is not None else CONFIG_DIR / "expert.toml"
    data = load_toml(path)
    values: dict[str, Any] = {}
    expected: dict[str, set[str]] = {}
    for f in fields(MpcConfig):
        expected.setdefault(f.metadata["table"], set()).add(f.name)
    for table, names in expected.items():
        tbl = data.get(table)
        if not isinstance(tbl, dict):
            raise ConfigError(f"{path}: missing table [{table}]")
        unknown = sorted(set(tbl) - names)
        if unknown:
            raise ConfigError(f"{path}: [{table}] unknown key(s) {unknown} (typo?)")
        for name in sorted(names):
            if name not in tbl:
                raise ConfigError(f"{path}: [{table}] missing key {name!r}")
    unknown_tables = sorted(set(data) - set(expected))
    if unknown_tables:
        raise ConfigError(f"{path}: unknown table(s) {unknown_tables}")
    for f in fields(MpcConfig):
        table = f.metadata["table"]
        values[f.name] = _check_value(
            data[table][f.name], dict(f.metadata), f"{path}: [{table}] {f.name}"
        )
    try:
        return MpcConfig(**values)
    except ConfigError as exc:  # cross-field checks: say which file
        raise ConfigError(f"{path}: {exc}") from None


# --------------------------------------------------------------------------- model


class ModelState(IntEnum):
    """Indices of the MPC model state (NED position m, NED velocity m/s, ZYX Euler rad)."""

    N = 0
    E = 1
    D = 2
    VN = 3
    VE = 4
    VD = 5
    ROLL = 6
    PITCH = 7
    YAW = 8


class ModelInput(IntEnum):
    """Indices of the MPC model input: the Command (thrust_norm, FRD body rates rad/s)."""

    THRUST = 0
    P = 1
    Q = 2
    R = 3


NX = len(ModelState)
NU = len(ModelInput)
_EULER = slice(ModelState.ROLL, ModelState.YAW + 1)
_VEL = slice(ModelState.VN, ModelState.VD + 1)
_QUAT_STEP = 1e-6  # s: central-difference step of the Euler angles along the quaternion rate
_OSQP_RHO = 0.1  # OSQP's initial ADMM step size (its default), restored at every episode start


def model_derivative(phys: Physics, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``f(x, u)``: time derivative (9,) of the MPC state for input ``u`` (4,).

    Everything comes from ``sitl_sim.dynamics.derivative`` at rotor thrusts that give the
    collective ``thrust_norm * T_max`` with zero torque (equal rotors), body rates equal to the
    commanded ones (ideal rate loop): position and velocity rates directly, and the Euler-angle
    rates as the central difference of ``euler_from_quat`` along the quaternion rate.
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    quat = quat_from_euler(*x[_EULER])
    rotor_n = (float(u[ModelInput.THRUST]) * phys.vehicle.max_total_thrust_n / 4.0,) * 4
    x17 = make_state(
        pos_ned_m=x[ModelState.N : ModelState.D + 1],
        vel_ned_m_s=x[_VEL],
        quat_wxyz=quat,
        rate_frd_rad_s=u[ModelInput.P : ModelInput.R + 1],
        rotor_thrust_n=rotor_n,
    )
    d = np.asarray(derivative(x17.tolist(), rotor_n, phys))
    qdot = d[6:10]
    plus = quat + _QUAT_STEP * qdot
    minus = quat - _QUAT_STEP * qdot
    euler_plus = euler_from_quat(plus / np.linalg.norm(plus))
    euler_minus = euler_from_quat(minus / np.linalg.norm(minus))
    euler_rate = (euler_plus - euler_minus) / (2.0 * _QUAT_STEP)
    return np.concatenate((d[0:6], euler_rate))


@dataclass(frozen=True)
class HoverModel:
    """The model linearised about hover and discretised by zero-order hold.

    Attributes:
        a: (9, 9) continuous ``df/dx`` at hover.
        b: (9, 4) continuous ``df/du`` at hover.
        a_d: (9, 9) discrete state matrix over ``dt_s``.
        b_d: (9, 4) discrete input matrix over ``dt_s`` (input held).
        gamma_d: (9, 9) ``int_0^dt expm(a s) ds``: maps a constant continuous residual
            (9,) to its effect over one step.
        u_hover: (4,) hover input (thrust_norm = m g / T_max, zero rates).
        dt_s: control period.
    """

    a: np.ndarray
    b: np.ndarray
    a_d: np.ndarray
    b_d: np.ndarray
    gamma_d: np.ndarray
    u_hover: np.ndarray
    dt_s: float


def linearise_hover(phys: Physics, dt_s: float, eps: float = 1e-4) -> HoverModel:
    """Central-difference Jacobians of :func:`model_derivative` at hover, then ZOH over ``dt_s``."""
    x0 = np.zeros(NX)
    u0 = np.zeros(NU)
    u0[ModelInput.THRUST] = phys.mass * phys.g / phys.vehicle.max_total_thrust_n
    a = np.empty((NX, NX))
    b = np.empty((NX, NU))
    for i in range(NX):
        dx = np.zeros(NX)
        dx[i] = eps
        a[:, i] = (model_derivative(phys, x0 + dx, u0) - model_derivative(phys, x0 - dx, u0)) / (
            2.0 * eps
        )
    for j in range(NU):
        du = np.zeros(NU)
        du[j] = eps
        b[:, j] = (model_derivative(phys, x0, u0 + du) - model_derivative(phys, x0, u0 - du)) / (
            2.0 * eps
        )
    # One matrix exponential gives A_d, B_d and the residual map (Van Loan's block trick).
    m = np.zeros((NX + NU + NX, NX + NU + NX))
    m[:NX, :NX] = a
    m[:NX, NX : NX + NU] = b
    m[:NX, NX + NU :] = np.eye(NX)
    e = expm(m * dt_s)
    return HoverModel(
        a=a,
        b=b,
        a_d=e[:NX, :NX],
        b_d=e[:NX, NX : NX + NU],
        gamma_d=e[:NX, NX + NU :],
        u_hover=u0,
        dt_s=float(dt_s),
    )


# --------------------------------------------------------------------------- records and errors


class MpcSolveError(PolicyError, RuntimeError):
    """Neither OSQP nor the Clarabel fallback solved the MPC's QP at this state.

    Attributes:
        osqp_status: OSQP's status string.
        clarabel_status: Clarabel's status string.
    """

    def __init__(self, message: str, osqp_status: str, clarabel_status: str) -> None:
        super().__init__(message)
        self.osqp_status = osqp_status
        self.clarabel_status = clarabel_status


@dataclass(frozen=True)
class MpcStats:
    """Solve counts since construction (or :meth:`MpcExpert.reset_stats`).

    Attributes:
        solves: QPs attempted.
        unsolved_osqp: OSQP returned a status other than solved (its answer was discarded).
        fallback_used: Clarabel solved the QP OSQP did not; its answer was used.
        failed: neither solver solved it; :class:`MpcSolveError` was raised.
    """

    solves: int = 0
    unsolved_osqp: int = 0
    fallback_used: int = 0
    failed: int = 0


@dataclass(frozen=True)
class MpcState:
    """The expert's policy state: the heading held during the episode (rad, NED yaw).

    ``None`` before the first step; the first step holds the yaw it finds.
    """

    yaw_hold_rad: float | None = None


@dataclass(frozen=True)
class MpcPlan:
    """One MPC solution.

    Attributes:
        command: the first input, the command to send now.
        mode: ``"far"`` or ``"near"`` (the cost set the proximity switch chose).
        solver: ``"osqp"`` or ``"clarabel"`` (the fallback).
        solve_time_s: wall time of the solver call(s).
        iterations: iterations of the solver whose answer was used.
        states: (N + 1, 9) predicted states in the heading frame, row 0 the current state.
        inputs: (N, 4) planned inputs (thrust_norm, p, q, r).
    """

    command: Command
    mode: str
    solver: str
    solve_time_s: float
    iterations: int
    states: np.ndarray
    inputs: np.ndarray


# --------------------------------------------------------------------------- the expert


def _wrap_pi(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class _Qp:
    """The sparse QP's fixed matrices and the index layout of ``z`` (built once)."""

    def __init__(self, model: HoverModel, cfg: MpcConfig, phys: Physics) -> None:
        n = cfg.horizon_steps
        self.n = n
        self.nx_all = n * NX
        self.nu_all = n * NU
        self.nz = self.nx_all + self.nu_all + n
        self.u0 = self.nx_all  # first input variable
        self.s0 = self.nx_all + self.nu_all  # first slack variable
        eye_n = sp.identity(n, format="csc")
        # Dynamics: -x_{k+1} + A_d x_k + B_d du_k = -c  (k = 0: A_d x_0 moves to the bound).
        ax = sp.kron(eye_n, -sp.identity(NX)) + sp.kron(sp.eye(n, k=-1), model.a_d)
        aeq = sp.hstack([ax, sp.kron(eye_n, model.b_d), sp.csc_matrix((self.nx_all, n))])
        # Tilt of each x_k (hard, two-sided): |roll|, |pitch| <= bound_k. The bounds are set per
        # solve (a funnel from a tilt beyond the limit back to it, see MpcExpert.plan), so the
        # QP stays feasible at any state a learner may reach.
        tilt_sel = np.zeros((2, NX))
        tilt_sel[0, ModelState.ROLL] = tilt_sel[1, ModelState.PITCH] = 1.0
        a_tilt = sp.hstack([sp.kron(eye_n, tilt_sel), sp.csc_matrix((2 * n, self.nu_all + n))])
        # Soft constraints of each x_k, relaxed by the step's slack s_k >= 0 with an exact
        # penalty (met whenever they can be; best effort, not infeasibility, when they cannot):
        #   down - s <= ground_margin,  v_down + slope * down - s <= at_ground  (down = -alt).
        soft = np.zeros((2, NX))
        soft[0, ModelState.D] = 1.0
        soft[1, ModelState.VD] = 1.0
        soft[1, ModelState.D] = cfg.descent_limit_slope_1_s
        a_soft = sp.hstack(
            [
                sp.kron(eye_n, soft),
                sp.csc_matrix((2 * n, self.nu_all)),
                sp.kron(eye_n, -np.ones((2, 1))),
            ]
        )
        a_slack = sp.hstack([sp.csc_matrix((n, self.nx_all + self.nu_all)), eye_n])
        a_input = sp.hstack(
            [
                sp.csc_matrix((self.nu_all, self.nx_all)),
                sp.identity(self.nu_all),
                sp.csc_matrix((self.nu_all, n)),
            ]
        )
        self.a = sp.vstack([aeq, a_tilt, a_soft, a_slack, a_input], format="csc")
        self.n_eq = self.nx_all
        self.tilt_rows = slice(self.n_eq, self.n_eq + 2 * n)  # rows of the tilt bounds in l, u
        self.steps = np.arange(1, n + 1)[:, None]  # (N, 1): k of x_k
        rate_rp = np.array(phys.vehicle.rate_controller.max_rate_rad_s[:2])
        self.tilt_funnel_rad = 0.5 * rate_rp * model.dt_s  # (2,): roll, pitch per step
        # Fixed bounds of the inequality rows (the tilt rows are overwritten per solve).
        self.max_tilt_rad = math.radians(cfg.max_tilt_deg)
        inf = np.inf
        tilt = np.full(2 * n, self.max_tilt_rad)
        soft_hi = np.tile([cfg.ground_margin_m, cfg.descent_limit_at_ground_m_s], n)
        u_hover = model.u_hover
        thrust_max = min(
            1.0, cfg.max_thrust_mg * phys.mass * phys.g / phys.vehicle.max_total_thrust_n
        )
        rates = phys.vehicle.rate_controller.max_rate_rad_s
        u_lo = np.array([0.0, *(-r for r in rates)]) - u_hover
        u_hi = np.array([thrust_max, *rates]) - u_hover
        lo = np.concatenate((-tilt, np.full(2 * n, -inf), np.zeros(n), np.tile(u_lo, n)))
        hi = np.concatenate((tilt, soft_hi, np.full(n, inf), np.tile(u_hi, n)))
        self.l_template = np.concatenate((np.zeros(self.n_eq), lo))
        self.u_template = np.concatenate((np.zeros(self.n_eq), hi))
        self.u_lo = u_lo + u_hover  # absolute input bounds, for clipping within tolerance
        self.u_hi = u_hi + u_hover

    def cost_diagonal(self, cfg: MpcConfig, pos_ne: float, vel_ne: float) -> np.ndarray:
        """(nz,) diagonal of the quadratic cost (weights, not yet doubled for OSQP's 1/2 z'Pz)."""
        q = np.zeros(NX)
        q[[ModelState.N, ModelState.E]] = pos_ne
        q[[ModelState.VN, ModelState.VE]] = vel_ne
        q[ModelState.D] = cfg.pos_d
        q[ModelState.VD] = cfg.vel_d
        q[[ModelState.ROLL, ModelState.PITCH]] = cfg.tilt
        q[ModelState.YAW] = cfg.yaw
        q_terminal = q.copy()
        q_terminal[[ModelState.N, ModelState.E]] += cfg.terminal_pos_ne
        q_terminal[[ModelState.VN, ModelState.VE]] += cfg.terminal_vel_ne
        r = np.array([cfg.thrust_norm, cfg.rate_roll_pitch, cfg.rate_roll_pitch, cfg.rate_yaw])
        return np.concatenate(
            (
                np.tile(q, self.n - 1),
                q_terminal,
                np.tile(r, self.n),
                np.full(self.n, cfg.slack_quadratic),
            )
        )


class MpcExpert:
    """Privileged MPC lander: ground truth in, :class:`Command` out (the :class:`Policy` API).

    Args:
        vehicle: the vehicle (mass, T_max, drag, rate limits are read from it).
        sim: the simulation config: its planet and control period.
        config: the MPC tuning (default: ``configs/expert.toml``).
    """

    privileged = True

    def __init__(
        self, vehicle: VehicleConfig, sim: SimConfig, config: MpcConfig | None = None
    ) -> None:
        self.config = config if config is not None else load_mpc_config()
        self.vehicle = vehicle
        self.phys = Physics(vehicle, sim.planet)
        self.model = linearise_hover(self.phys, sim.control_dt_s)
        cfg = self.config
        self._qp = _Qp(self.model, cfg, self.phys)
        self._hover_thrust_n = self.phys.mass * self.phys.g
        rc = vehicle.rate_controller
        self._rate_lag_s = np.array(
            [1.0 / kp + vehicle.motor_time_constant_s if kp > 0.0 else 0.0 for kp in rc.kp]
        )
        qp = self._qp
        self._weights: dict[str, np.ndarray] = {}
        self._solvers: dict[str, osqp.OSQP] = {}
        for mode, pos_ne, vel_ne in (
            ("far", cfg.far_pos_ne, cfg.far_vel_ne),
            ("near", cfg.near_pos_ne, cfg.near_vel_ne),
        ):
            w = qp.cost_diagonal(cfg, pos_ne, vel_ne)
            self._weights[mode] = w
            solver = osqp.OSQP()
            solver.setup(
                sp.diags(2.0 * w, format="csc"),
                np.zeros(qp.nz),
                qp.a,
                qp.l_template,
                qp.u_template,
                verbose=False,
                eps_abs=cfg.osqp_eps_abs,
                eps_rel=cfg.osqp_eps_rel,
                max_iter=cfg.osqp_max_iter,
                polishing=False,
                warm_starting=True,
                rho=_OSQP_RHO,
                # A fixed rho-adaptation interval (not a fraction of setup time) keeps the
                # iterates, and so the flights, bit-for-bit reproducible.
                adaptive_rho_interval=25,
            )
            self._solvers[mode] = solver
        self._counts = {"solves": 0, "unsolved_osqp": 0, "fallback_used": 0, "failed": 0}
        self.last_plan: MpcPlan | None = None
        """The plan behind the latest :meth:`act` command (predicted trajectory, solver, time)."""

    # ------------------------------------------------------------------ Policy API

    def initial_state(self) -> MpcState:
        """A new episode. Also returns both OSQP instances to their just-set-up state (cold
        iterate and the initial step size rho, which OSQP adapts while solving), so an episode's
        commands never depend on which episodes this instance flew before: one worker and N
        workers fly the same flights, bit for bit."""
        for solver in self._solvers.values():
            solver.update_settings(rho=_OSQP_RHO)
            solver.warm_start(x=np.zeros(self._qp.nz), y=np.zeros(self._qp.a.shape[0]))
        return MpcState()

    def act(
        self,
        observation: Observation,
        groundtruth: GroundTruth | None,
        state: MpcState,
    ) -> tuple[Command, MpcState]:
        """The MPC command at ``groundtruth`` (the observation is not needed: privileged).

        Raises:
            MissingGroundTruthError: ``groundtruth`` is None.
            MpcSolveError: neither OSQP nor Clarabel solved the QP.
        """
        if groundtruth is None:
            raise MissingGroundTruthError(
                "MpcExpert is a privileged policy: act() needs groundtruth (a "
                "sitl_sim.simulator.GroundTruth); it cannot fly from an Observation alone"
            )
        yaw_hold = state.yaw_hold_rad
        if yaw_hold is None:
            yaw_hold = float(euler_from_quat(groundtruth.quat_wxyz)[2])
            state = MpcState(yaw_hold_rad=yaw_hold)
        self.last_plan = None  # a failed solve must not leave the previous plan looking current
        plan = self.plan(
            groundtruth.pos_ned_m,
            groundtruth.vel_ned_m_s,
            groundtruth.quat_wxyz,
            yaw_hold,
            groundtruth.rate_frd_rad_s,
        )
        self.last_plan = plan
        return plan.command, state

    # ------------------------------------------------------------------ solving

    @property
    def stats(self) -> MpcStats:
        """A snapshot of the solve counts."""
        return MpcStats(**self._counts)

    def reset_stats(self) -> None:
        for key in self._counts:
            self._counts[key] = 0

    def _lead_attitude(self, quat: np.ndarray, rate_frd_rad_s: np.ndarray) -> np.ndarray:
        """The attitude after the body rotation still under way has died out.

        The autopilot's rate loop (``w' = kp (w_cmd - w)``, then the rotor lag) follows a new
        rate setpoint with a lag of about ``1/kp + motor_time_constant`` per axis; the model
        takes rates as instantaneous. Rotating the start attitude by ``w * lag`` puts that
        rotation where the model can see it (a Smith-predictor-like lead; all constants read
        from the vehicle config).
        """
        x17 = make_state(quat_wxyz=quat, rate_frd_rad_s=rate_frd_rad_s * self._rate_lag_s)
        qdot = np.asarray(derivative(x17.tolist(), (0.0,) * 4, self.phys)[6:10])
        lead = quat + qdot  # one unit-time Euler step of q' = q (x) (0, w lag) / 2
        return lead / np.linalg.norm(lead)

    def _reference(self, altitude_m: float, horizontal_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference altitude (m) and downward speed (m/s) at steps 1..N of the descent profile.

        The profile is ``clip(gain * altitude, touchdown, max)``, scaled by the approach cone
        ``clip(1 - slope * max(d - deadband, 0) / altitude, 0, 1)`` of the horizontal distance
        ``d`` to the pad: far off the pad (a learner's DAgger state, say) the expert flies over
        the pad first instead of touching down short of it; on the pad the cone is inactive.
        """
        cfg = self.config
        dt = self.model.dt_s
        n = cfg.horizon_steps
        off_cone = cfg.approach_slope * max(horizontal_m - cfg.approach_deadband_m, 0.0)
        h = max(altitude_m, 0.0)
        alt = np.empty(n)
        v_down = np.empty(n)

        def speed(height: float) -> float:
            profile = min(
                cfg.max_descent_m_s, max(cfg.touchdown_descent_m_s, cfg.descent_gain_1_s * height)
            )
            if off_cone <= 0.0:
                return profile
            return profile * min(1.0, max(0.0, 1.0 - off_cone / max(height, 1e-6)))

        for k in range(n):
            h = max(h - speed(h) * dt, 0.0)
            alt[k] = h
            v_down[k] = speed(h)
        return alt, v_down

    def plan(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_m_s: np.ndarray,
        quat_wxyz: np.ndarray,
        yaw_hold_rad: float | None = None,
        rate_frd_rad_s: np.ndarray | None = None,
    ) -> MpcPlan:
        """Solve the MPC at one state (ground truth, NED/FRD) and return the plan.

        Args:
            pos_ned_m: (3,) position, pad centre = origin.
            vel_ned_m_s: (3,) velocity.
            quat_wxyz: (4,) attitude, body FRD -> NED.
            yaw_hold_rad: heading to hold (default: the current yaw).
            rate_frd_rad_s: (3,) current body rates; when given, the attitude the model starts
                from is led by the rotation still under way (see :meth:`_lead_attitude`).

        Raises:
            MpcSolveError: neither OSQP nor Clarabel solved the QP.
        """
        cfg = self.config
        qp = self._qp
        model = self.model
        quat = np.asarray(quat_wxyz, dtype=float)
        if rate_frd_rad_s is not None:
            quat = self._lead_attitude(quat, np.asarray(rate_frd_rad_s, dtype=float))
        roll, pitch, yaw = (float(v) for v in euler_from_quat(quat))
        if yaw_hold_rad is None:
            yaw_hold_rad = yaw
        # Heading frame: rotate horizontal position and velocity by -yaw (model yaw = 0).
        c, s = math.cos(yaw), math.sin(yaw)
        pn, pe, pd = (float(v) for v in pos_ned_m)
        vn, ve, vd = (float(v) for v in vel_ned_m_s)
        # (9,) in ModelState order: N, E, D, VN, VE, VD, roll, pitch, yaw (0 in this frame).
        x0 = np.array(
            [
                c * pn + s * pe,
                -s * pn + c * pe,
                pd,
                c * vn + s * ve,
                -s * vn + c * ve,
                vd,
                roll,
                pitch,
                0.0,
            ]
        )
        # Affine residual of the nonlinear model at x0 with hover input (mostly body drag).
        acc = translational_accel_ned(
            quat_from_euler(roll, pitch, 0.0), x0[_VEL], self._hover_thrust_n, self.phys
        )
        resid = np.zeros(NX)
        resid[_VEL] = np.asarray(acc) - model.a[_VEL] @ x0
        c_d = model.gamma_d @ resid
        # Equality bounds: -x1 + B du0 = -(A x0 + c); -x_{k+1} + A x_k + B du_k = -c.
        beq = np.tile(-c_d, qp.n)
        beq[:NX] -= model.a_d @ x0
        lo = qp.l_template.copy()
        hi = qp.u_template.copy()
        lo[: qp.n_eq] = beq
        hi[: qp.n_eq] = beq
        # Tilt bounds: the limit, or — from a state beyond it — a funnel closing in at half the
        # rate limit (reachable in the model, so the QP is feasible from any attitude).
        tilt_k = np.maximum(
            qp.max_tilt_rad, np.abs(np.array([roll, pitch])) - qp.tilt_funnel_rad * qp.steps
        ).ravel()
        lo[qp.tilt_rows] = -tilt_k
        hi[qp.tilt_rows] = tilt_k
        # Reference trajectory and the proximity switch of the paper.
        alt_ref, vd_ref = self._reference(-pd, math.hypot(pn, pe))
        ref = np.zeros((qp.n, NX))
        ref[:, ModelState.D] = -alt_ref
        ref[:, ModelState.VD] = vd_ref
        ref[:, ModelState.YAW] = _wrap_pi(yaw_hold_rad - yaw)
        mode = "near" if math.sqrt(pn * pn + pe * pe + pd * pd) <= cfg.near_distance_m else "far"
        w = self._weights[mode]
        q = np.zeros(qp.nz)
        q[: qp.nx_all] = -2.0 * w[: qp.nx_all] * ref.ravel()
        q[qp.s0 :] = cfg.slack_linear
        z, solver_name, iters, solve_time = self._solve(mode, q, lo, hi)
        du = z[qp.u0 : qp.s0].reshape(qp.n, NU)
        inputs = du + model.u_hover
        states = np.vstack((x0, z[: qp.nx_all].reshape(qp.n, NX)))
        # The solver meets bounds to its tolerance (~1e-4): project the command into the
        # contract's range so a solved answer is never rejected by Command's validation.
        u_cmd = np.clip(inputs[0], qp.u_lo, qp.u_hi)
        command = Command(
            thrust_norm=float(u_cmd[ModelInput.THRUST]),
            rate_frd_rad_s=u_cmd[ModelInput.P : ModelInput.R + 1],
        )
        return MpcPlan(
            command=command,
            mode=mode,
            solver=solver_name,
            solve_time_s=solve_time,
            iterations=iters,
            states=states,
            inputs=inputs,
        )

    def _solve(
        self, mode: str, q: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> tuple[np.ndarray, str, int, float]:
        """OSQP, then Clarabel on the same QP; returns (z, solver, iterations, wall time s)."""
        self._counts["solves"] += 1
        solver = self._solvers[mode]
        t0 = time.perf_counter()
        solver.update(q=q, l=lo, u=hi)
        res = solver.solve(raise_error=False)
        elapsed = time.perf_counter() - t0
        osqp_status = str(res.info.status)
        if res.info.status_val == osqp.SolverStatus.OSQP_SOLVED and np.all(np.isfinite(res.x)):
            return res.x, "osqp", int(res.info.iter), elapsed
        self._counts["unsolved_osqp"] += 1
        t0 = time.perf_counter()
        z, clarabel_status, iters = self._solve_clarabel(mode, q, lo, hi)
        elapsed += time.perf_counter() - t0
        if z is None:
            self._counts["failed"] += 1
            raise MpcSolveError(
                f"MPC QP not solved: OSQP status {osqp_status!r}, Clarabel fallback status "
                f"{clarabel_status!r}; no command was produced",
                osqp_status=osqp_status,
                clarabel_status=clarabel_status,
            )
        self._counts["fallback_used"] += 1
        solver.warm_start(x=z)  # restart OSQP next step from the good answer, not its iterate
        return z, "clarabel", iters, elapsed

    def _solve_clarabel(
        self, mode: str, q: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> tuple[np.ndarray | None, str, int]:
        """The same QP with Clarabel's direct API: ``l <= A z <= u`` as zero + nonnegative cones."""
        a = self._qp.a
        eq = lo == hi
        upper = ~eq & np.isfinite(hi)
        lower = ~eq & np.isfinite(lo)
        a_cl = sp.vstack([a[eq], a[upper], -a[lower]], format="csc")
        b_cl = np.concatenate((hi[eq], hi[upper], -lo[lower]))
        cones = [
            clarabel.ZeroConeT(int(eq.sum())),
            clarabel.NonnegativeConeT(int(upper.sum() + lower.sum())),
        ]
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.max_iter = self.config.clarabel_max_iter
        p = sp.triu(sp.diags(2.0 * self._weights[mode]), format="csc")
        solver = clarabel.DefaultSolver(p, q, a_cl, b_cl, cones, settings)
        sol = solver.solve()
        status = str(sol.status)
        z = np.asarray(sol.x)
        if sol.status != clarabel.SolverStatus.Solved or not np.all(np.isfinite(z)):
            return None, status, int(sol.iterations)
        return z, status, int(sol.iterations)
