"""The MPC expert's QP: its sparse matrices and variable layout, and solving it.

Variables ``z = [x_1..x_N, du_0..du_{N-1}, s_1..s_N]``, with ``du = u - u_hover`` and
``s_k >= 0`` one slack per step for the soft constraints. Cost: control effort about hover;
tracking of a descent-speed profile that slows down near the ground; and, as the paper's
proximity switch, two cost sets: *far* (efficiency first, the pad only as a terminal cost) and
*near* (a position-tracking cost at every step). Each cost set has its own OSQP instance, set up
once; per step only the vectors ``q``, ``l``, ``u`` change. Constraints:

* dynamics;
* ``0 <= thrust <= max_thrust_mg * m g``, body rates within the autopilot's ``max_rate_rad_s``;
* ``|roll|, |pitch| <= max_tilt_deg`` (hard; from a state already beyond it, a funnel back to it
  that the rate limits can follow, so the QP is feasible from any attitude), closing to
  ``touchdown_tilt_deg`` over the steps whose reference altitude is in the last
  ``touchdown_tilt_height_m`` (set per solve by ``MpcExpert.plan``);
* soft, with an exact (linear + quadratic) slack penalty so they hold whenever they can and a
  state a learner drove too low or too fast still gets a best-effort label: altitude
  ``>= -ground_margin_m`` (paper: ``z >= 0``; touchdown is an event the plan flies through, not
  a state it must stop at) and downward speed ``<= at_ground + slope * altitude`` (what makes
  the touchdown soft).

A solve whose status is not *solved* is never used: the same QP goes to Clarabel (interior
point, direct API), and if that fails too :class:`MpcSolveError` is raised for the caller to
record. :attr:`MpcQp.counts` counts the outcomes.
"""

from __future__ import annotations

import math
import time

import clarabel
import numpy as np
import osqp
import scipy.sparse as sp

from companion.contract import PolicyError
from expert.mpc.config import MpcConfig
from expert.mpc.model import NU, NX, HoverModel, ModelState
from sitl_sim.physics.dynamics import Physics

__all__ = ["MpcQp", "MpcSolveError"]

_OSQP_RHO = 0.1  # OSQP's initial ADMM step size (its default), restored at every episode start


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


class MpcQp:
    """The sparse QP's fixed matrices, the index layout of ``z`` and its solvers (built once).

    One OSQP instance per cost set (``"far"``, ``"near"``), set up here; :meth:`solve` updates
    only ``q``, ``l``, ``u`` and falls back to Clarabel on the same QP.
    """

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
        thrust_max = min(1.0, cfg.max_thrust_mg * phys.mass * phys.g / phys.max_total_thrust_n)
        rates = phys.vehicle.rate_controller.max_rate_rad_s
        u_lo = np.array([0.0, *(-r for r in rates)]) - u_hover
        u_hi = np.array([thrust_max, *rates]) - u_hover
        lo = np.concatenate((-tilt, np.full(2 * n, -inf), np.zeros(n), np.tile(u_lo, n)))
        hi = np.concatenate((tilt, soft_hi, np.full(n, inf), np.tile(u_hi, n)))
        self.l_template = np.concatenate((np.zeros(self.n_eq), lo))
        self.u_template = np.concatenate((np.zeros(self.n_eq), hi))
        self.u_lo = u_lo + u_hover  # absolute input bounds, for clipping within tolerance
        self.u_hi = u_hi + u_hover
        self._clarabel_max_iter = cfg.clarabel_max_iter
        self.weights: dict[str, np.ndarray] = {}
        """Per cost set, the diagonal of the quadratic cost (:meth:`cost_diagonal`)."""
        self._solvers: dict[str, osqp.OSQP] = {}
        for mode, pos_ne, vel_ne in (
            ("far", cfg.far_pos_ne, cfg.far_vel_ne),
            ("near", cfg.near_pos_ne, cfg.near_vel_ne),
        ):
            w = self.cost_diagonal(cfg, pos_ne, vel_ne)
            self.weights[mode] = w
            solver = osqp.OSQP()
            solver.setup(
                sp.diags(2.0 * w, format="csc"),
                np.zeros(self.nz),
                self.a,
                self.l_template,
                self.u_template,
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
        self.counts = {"solves": 0, "unsolved_osqp": 0, "fallback_used": 0, "failed": 0}
        """Solve outcomes: attempted, OSQP unsolved, Clarabel used, both failed."""

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

    def reset(self) -> None:
        """Both OSQP instances back to their just-set-up state: cold iterate and the initial
        step size rho (which OSQP adapts while solving)."""
        for solver in self._solvers.values():
            solver.update_settings(rho=_OSQP_RHO)
            solver.warm_start(x=np.zeros(self.nz), y=np.zeros(self.a.shape[0]))

    def solve(
        self, mode: str, q: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> tuple[np.ndarray, str, int, float]:
        """OSQP, then Clarabel on the same QP; returns (z, solver, iterations, wall time s).

        Raises:
            MpcSolveError: neither solver solved it.
        """
        self.counts["solves"] += 1
        solver = self._solvers[mode]
        t0 = time.perf_counter()
        solver.update(q=q, l=lo, u=hi)
        res = solver.solve(raise_error=False)
        elapsed = time.perf_counter() - t0
        osqp_status = str(res.info.status)
        if res.info.status_val == osqp.SolverStatus.OSQP_SOLVED and np.all(np.isfinite(res.x)):
            return res.x, "osqp", int(res.info.iter), elapsed
        self.counts["unsolved_osqp"] += 1
        t0 = time.perf_counter()
        z, clarabel_status, iters = self._solve_clarabel(mode, q, lo, hi)
        elapsed += time.perf_counter() - t0
        if z is None:
            self.counts["failed"] += 1
            raise MpcSolveError(
                f"MPC QP not solved: OSQP status {osqp_status!r}, Clarabel fallback status "
                f"{clarabel_status!r}; no command was produced",
                osqp_status=osqp_status,
                clarabel_status=clarabel_status,
            )
        self.counts["fallback_used"] += 1
        solver.warm_start(x=z)  # restart OSQP next step from the good answer, not its iterate
        return z, "clarabel", iters, elapsed

    def _solve_clarabel(
        self, mode: str, q: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> tuple[np.ndarray | None, str, int]:
        """The same QP with Clarabel's direct API: ``l <= A z <= u`` as zero + nonnegative cones."""
        a = self.a
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
        settings.max_iter = self._clarabel_max_iter
        p = sp.triu(sp.diags(2.0 * self.weights[mode]), format="csc")
        solver = clarabel.DefaultSolver(p, q, a_cl, b_cl, cones, settings)
        sol = solver.solve()
        status = str(sol.status)
        z = np.asarray(sol.x)
        if sol.status != clarabel.SolverStatus.Solved or not np.all(np.isfinite(z)):
            return None, status, int(sol.iterations)
        return z, status, int(sol.iterations)
