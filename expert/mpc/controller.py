"""The MPC expert itself (paper section 3.2): privileged state in, a Command out, per step.

:class:`MpcExpert` flies the linear MPC of :mod:`expert.mpc.model` and :mod:`expert.mpc.qp`
with the tuning of :mod:`expert.mpc.config`. Two cheap corrections, computed per solve from the
same physics, keep the hover model honest away from hover:

* the residual ``f(x0, u_hover) - A x0`` at the current state (mostly body drag, quadratic and
  so invisible to a hover linearisation; in wind the drag of the air-relative velocity, from the
  privileged ``GroundTruth.wind_ned_m_s``) is fed forward as a constant affine term;
* the rate loop follows a setpoint with a lag (``1/kp`` + rotor lag, from the vehicle config)
  the model does not have, so the start attitude is led by the rotation still under way.

Yaw. The model is linearised at yaw 0; every solve works in the *heading frame*: horizontal
position and velocity rotated by ``-yaw`` so the current yaw is 0 in the model. The heading held
is the one of the episode's first step (kept in the policy state, :class:`MpcState`); its error
is a state the MPC drives to zero with ``r``, and the rate loop damps any yaw rate.

Solve outcomes (OSQP, the Clarabel fallback, failures) are counted in :attr:`MpcExpert.stats`.

The model is the vehicle the expert was built for. An episode whose airframe is randomised (a
scenario's ``[vehicle]``) is flown by :meth:`MpcExpert.for_vehicle` of the episode's vehicle:
the expert is privileged and flies the true airframe, as it reads the true wind.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from companion.contract import Command, GroundTruth, MissingGroundTruthError, Observation
from expert.mpc.config import MpcConfig, load_mpc_config
from expert.mpc.model import NU, NX, VEL, ModelInput, ModelState, linearise_hover
from expert.mpc.qp import MpcQp
from sitl_sim.config import SimConfig, VehicleConfig
from sitl_sim.physics.dynamics import (
    Physics,
    derivative,
    euler_from_quat,
    make_state,
    quat_from_euler,
    translational_accel_ned,
)

__all__ = ["MpcExpert", "MpcPlan", "MpcState", "MpcStats"]


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


_OTHER_VEHICLES = 8
"""Experts for other vehicles kept by :meth:`MpcExpert.for_vehicle` (least recently used out):
re-flying or relabelling an episode finds its expert; a stream of fresh draws stays bounded."""


def _wrap_pi(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


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
        self.sim = sim
        self.phys = Physics(vehicle, sim.planet)
        self.model = linearise_hover(self.phys, sim.control_dt_s)
        cfg = self.config
        self._qp = MpcQp(self.model, cfg, self.phys)
        self._hover_thrust_n = self.phys.mass * self.phys.g
        rc = vehicle.rate_controller
        self._rate_lag_s = np.array(
            [1.0 / kp + vehicle.motor_time_constant_s if kp > 0.0 else 0.0 for kp in rc.kp]
        )
        self.last_plan: MpcPlan | None = None
        """The plan behind the latest :meth:`act` command (predicted trajectory, solver, time)."""
        self._others: OrderedDict[VehicleConfig, MpcExpert] = OrderedDict()

    def for_vehicle(self, vehicle: VehicleConfig) -> MpcExpert:
        """The expert for ``vehicle`` (same tuning, planet and control period): this one when
        it already flies it (the nominal path builds nothing), else one re-linearised for it
        and kept (up to :data:`_OTHER_VEHICLES`, keyed by the frozen VehicleConfig)."""
        if vehicle == self.vehicle:
            return self
        expert = self._others.pop(vehicle, None)
        if expert is None:
            expert = MpcExpert(vehicle, self.sim, self.config)
            if len(self._others) >= _OTHER_VEHICLES:
                self._others.popitem(last=False)
        self._others[vehicle] = expert
        return expert

    # ------------------------------------------------------------------ Policy API

    def initial_state(self) -> MpcState:
        """A new episode. Also returns both OSQP instances to their just-set-up state (cold
        iterate and the initial step size rho, which OSQP adapts while solving), so an episode's
        commands never depend on which episodes this instance flew before: one worker and N
        workers fly the same flights, bit for bit."""
        self._qp.reset()
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
                "companion.contract.GroundTruth); it cannot fly from an Observation alone"
            )
        yaw_hold = state.yaw_hold_rad
        if yaw_hold is None:
            yaw_hold = float(euler_from_quat(groundtruth.quat_wxyz)[2])
            state = MpcState(yaw_hold_rad=yaw_hold)
        self.last_plan = None  # a failed solve must not leave the previous plan looking current
        # Tracking in the pad's frame: the state relative to the pad's surface centre; the air
        # seen from that frame moves at wind - pad velocity (the drag stays the true one), and
        # the pad's acceleration (a rover's turn, a deck's heave) is fed forward as the frame's.
        pos, vel = groundtruth.pad_relative
        wind = groundtruth.wind_ned_m_s
        frame_accel = groundtruth.pad_accel_ned_m_s2
        if groundtruth.pad_vel_ned_m_s is not None:
            wind = (0.0 if wind is None else wind) - groundtruth.pad_vel_ned_m_s
        plan = self.plan(
            pos,
            vel,
            groundtruth.quat_wxyz,
            yaw_hold,
            groundtruth.rate_frd_rad_s,
            wind,
            frame_accel,
        )
        self.last_plan = plan
        return plan.command, state

    # ------------------------------------------------------------------ solving

    @property
    def stats(self) -> MpcStats:
        """A snapshot of the solve counts."""
        return MpcStats(**self._qp.counts)

    def reset_stats(self) -> None:
        for key in self._qp.counts:
            self._qp.counts[key] = 0

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

    def _tilt_limit(self, alt_ref: np.ndarray) -> np.ndarray:
        """(N,) roll and pitch bound (rad) of steps 1..N from their reference altitude (m).

        ``max_tilt_deg`` up high; over the last ``touchdown_tilt_height_m`` it closes linearly
        to ``touchdown_tilt_deg`` at the ground. Why: success needs tilt <= 20 deg at contact,
        and in severe wind (16-21 m/s near the ground) holding station takes up to ~29 deg, so
        the expert touched down leaning into a gust. The plan's steps at the ground are bounded
        instead: the expert levels in the last few decimetres and accepts the drift that costs
        (tenths of a metre; the success radius is 1 m). In still air or light wind the tilt stays
        well inside the bound, which then never binds (nominal flights are unchanged bit for
        bit). docs/DESIGN.md's decisions log says why.
        """
        cfg = self.config
        hi = self._qp.max_tilt_rad
        td = math.radians(cfg.touchdown_tilt_deg)
        band = cfg.touchdown_tilt_height_m
        if band <= 0.0 or td >= hi:
            return np.full(alt_ref.shape, hi)
        return td + (hi - td) * np.clip(alt_ref / band, 0.0, 1.0)

    def plan(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_m_s: np.ndarray,
        quat_wxyz: np.ndarray,
        yaw_hold_rad: float | None = None,
        rate_frd_rad_s: np.ndarray | None = None,
        wind_ned_m_s: np.ndarray | None = None,
        frame_accel_ned_m_s2: np.ndarray | None = None,
    ) -> MpcPlan:
        """Solve the MPC at one state (ground truth, NED/FRD) and return the plan.

        Args:
            pos_ned_m: (3,) position, pad centre = origin.
            vel_ned_m_s: (3,) velocity.
            quat_wxyz: (4,) attitude, body FRD -> NED.
            yaw_hold_rad: heading to hold (default: the current yaw).
            rate_frd_rad_s: (3,) current body rates; when given, the attitude the model starts
                from is led by the rotation still under way (see :meth:`_lead_attitude`).
            wind_ned_m_s: (3,) the true wind now (privileged, ``GroundTruth.wind_ned_m_s``);
                its drag at the current state joins the affine residual, i.e. it is fed
                forward as a disturbance held over the horizon. None: still air.
            frame_accel_ned_m_s2: (3,) the acceleration of the frame ``pos_ned_m`` is given in
                (a moving pad's), held over the horizon: the relative motion's feed-forward.
                None: an inertial frame (the still pad).

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
        # Affine residual of the nonlinear model at x0 with hover input (mostly body drag; in
        # wind, the drag of the air-relative velocity: the wind's push, fed forward).
        wind_h = None
        if wind_ned_m_s is not None:
            wn, we, wd = (float(v) for v in wind_ned_m_s)
            wind_h = (c * wn + s * we, -s * wn + c * we, wd)  # heading frame, as x0
        acc = translational_accel_ned(
            quat_from_euler(roll, pitch, 0.0), x0[VEL], self._hover_thrust_n, self.phys, wind_h
        )
        resid = np.zeros(NX)
        resid[VEL] = np.asarray(acc) - model.a[VEL] @ x0
        if frame_accel_ned_m_s2 is not None:
            an, ae, ad = (float(v) for v in frame_accel_ned_m_s2)
            resid[VEL] -= np.array([c * an + s * ae, -s * an + c * ae, ad])
        c_d = model.gamma_d @ resid
        # Equality bounds: -x1 + B du0 = -(A x0 + c); -x_{k+1} + A x_k + B du_k = -c.
        beq = np.tile(-c_d, qp.n)
        beq[:NX] -= model.a_d @ x0
        lo = qp.l_template.copy()
        hi = qp.u_template.copy()
        lo[: qp.n_eq] = beq
        hi[: qp.n_eq] = beq
        # Reference trajectory and the proximity switch of the paper.
        alt_ref, vd_ref = self._reference(-pd, math.hypot(pn, pe))
        # Tilt bounds: the limit, or — from a state beyond it — a funnel closing in at half the
        # rate limit (reachable in the model, so the QP is feasible from any attitude).
        tilt_k = np.maximum(
            self._tilt_limit(alt_ref)[:, None],
            np.abs(np.array([roll, pitch])) - qp.tilt_funnel_rad * qp.steps,
        ).ravel()
        lo[qp.tilt_rows] = -tilt_k
        hi[qp.tilt_rows] = tilt_k
        ref = np.zeros((qp.n, NX))
        ref[:, ModelState.D] = -alt_ref
        ref[:, ModelState.VD] = vd_ref
        ref[:, ModelState.YAW] = _wrap_pi(yaw_hold_rad - yaw)
        mode = "near" if math.sqrt(pn * pn + pe * pe + pd * pd) <= cfg.near_distance_m else "far"
        w = qp.weights[mode]
        q = np.zeros(qp.nz)
        q[: qp.nx_all] = -2.0 * w[: qp.nx_all] * ref.ravel()
        q[qp.s0 :] = cfg.slack_linear
        z, solver_name, iters, solve_time = qp.solve(mode, q, lo, hi)
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
