"""How fast the MPC expert decides, against the paper's way of solving the same kind of problem.

:func:`bench_mpc` flies the expert over a few episodes of a scenario (physics only, no camera),
timing every :meth:`~expert.mpc.MpcExpert.plan` call as it happens in flight (warm-started, the
way it is used). In the same run it times, on a subsample of those same flight states, a
baseline that does what paper section 3.2 describes: the 12-state model (Euler angles, body
rates, position, velocity) with collective thrust and body torques as inputs, linearised about
hover, written in CVXPY and **rebuilt on every call**, solved with OSQP through CVXPY. The
baseline is there to be timed, not flown: its cost and constraints follow the paper (effort
about hover, a terminal-state cost whose weight switches near the target, thrust <= 2.5 m g,
|torque| <= 0.01 N m, roll/pitch <= 30 deg, altitude >= 0).
"""

from __future__ import annotations

import math
import statistics
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cvxpy as cp
import numpy as np
from scipy.linalg import expm

from companion.contract import GroundTruth
from expert.mpc import MpcConfig, MpcExpert, load_mpc_config
from sitl_sim.config import SimConfig, load_sim, load_vehicle
from sitl_sim.physics.dynamics import (
    Physics,
    derivative,
    euler_from_quat,
    make_state,
    quat_from_euler,
)
from sitl_sim.scenario import InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator

__all__ = ["MpcBenchConfig", "bench_mpc"]

_MAX_TORQUE_NM = 0.01  # paper 3.2: |body torque| <= 0.01 N m (the baseline's own limit)


@dataclass(frozen=True)
class MpcBenchConfig:
    """What :func:`bench_mpc` flies and how many baseline solves it times."""

    episodes: int = 3
    """Episodes flown by the expert; every control step is one timed solve."""
    baseline_samples: int = 40
    """Flight states (evenly spread) on which the CVXPY baseline is timed."""
    seed: int = 0
    """Scenario seed (episode ``i`` of this seed is the same flight everywhere)."""
    scenario: str | None = None
    """Scenario TOML (default ``configs/scenario.toml``)."""
    expert_config: str | None = None
    """MPC config TOML (default ``configs/expert.toml``)."""

    def __post_init__(self) -> None:
        if self.episodes < 1 or self.baseline_samples < 1:
            raise ValueError(
                f"episodes = {self.episodes}, baseline_samples = {self.baseline_samples}; "
                "expected both >= 1"
            )


def _percentile_ms(values_s: list[float], pct: float) -> float:
    return 1e3 * float(np.percentile(np.asarray(values_s), pct))


def _fly(
    sim: Simulator, expert: MpcExpert, sampler: InitialStateSampler, cfg: MpcBenchConfig
) -> tuple[list[float], list[float], list[GroundTruth]]:
    """Fly the expert; returns per-step wall times of plan(), of the solver, and the states."""
    walls: list[float] = []
    solver_times: list[float] = []
    states: list[GroundTruth] = []
    limit = round(sim.sim.episode_timeout_s * sim.sim.control_rate_hz)
    for episode in range(cfg.episodes):
        sim.reset(sampler.sample(episode), np.random.SeedSequence([cfg.seed, episode]))
        state = expert.initial_state()
        for _ in range(limit):
            truth = sim.ground_truth()
            t0 = time.perf_counter()
            command, state = expert.act(None, truth, state)  # type: ignore[arg-type]
            walls.append(time.perf_counter() - t0)
            if expert.last_plan is not None:
                solver_times.append(expert.last_plan.solve_time_s)
            states.append(truth)
            if sim.step(command) is not None:
                break
    return walls, solver_times, states


# --------------------------------------------------------------------------- the paper's baseline


class _PaperBaseline:
    """Paper 3.2: 12-state, thrust + torque input LTI MPC in CVXPY, rebuilt on every call."""

    NX = 12  # roll, pitch, yaw, p, q, r, north, east, down, v_n, v_e, v_d
    NU = 4  # collective thrust (N), torques about FRD x, y, z (N m)

    def __init__(self, phys: Physics, dt_s: float, cfg: MpcConfig) -> None:
        self.phys = phys
        self.cfg = cfg
        self.u_hover = np.array([phys.mass * phys.g, 0.0, 0.0, 0.0])
        a, b = self._jacobians()
        m = np.zeros((self.NX + self.NU, self.NX + self.NU))
        m[: self.NX, : self.NX] = a
        m[: self.NX, self.NX :] = b
        e = expm(m * dt_s)
        self.a_d = e[: self.NX, : self.NX]
        self.b_d = e[: self.NX, self.NX :]

    def _f(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The sim's derivative in the paper's 12-state layout (rotors at their commands)."""
        rotor = self.phys.allocation_inv @ u
        quat = quat_from_euler(*x[0:3])
        x17 = make_state(x[6:9], x[9:12], quat, x[3:6], rotor)
        d = np.asarray(derivative(x17.tolist(), rotor.tolist(), self.phys))
        h = 1e-6
        plus, minus = quat + h * d[6:10], quat - h * d[6:10]
        euler_rate = (
            euler_from_quat(plus / np.linalg.norm(plus))
            - euler_from_quat(minus / np.linalg.norm(minus))
        ) / (2 * h)
        return np.concatenate((euler_rate, d[10:13], d[0:3], d[3:6]))

    def _jacobians(self, eps: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
        x0 = np.zeros(self.NX)
        a = np.empty((self.NX, self.NX))
        b = np.empty((self.NX, self.NU))
        for i in range(self.NX):
            dx = np.zeros(self.NX)
            dx[i] = eps
            a[:, i] = (self._f(x0 + dx, self.u_hover) - self._f(x0 - dx, self.u_hover)) / (2 * eps)
        for j in range(self.NU):
            du = np.zeros(self.NU)
            du[j] = eps
            b[:, j] = (self._f(x0, self.u_hover + du) - self._f(x0, self.u_hover - du)) / (2 * eps)
        return a, b

    def solve(self, truth: GroundTruth) -> str:
        """Build the CVXPY problem for this state and solve it; returns CVXPY's status."""
        cfg = self.cfg
        n = cfg.horizon_steps
        x0 = np.concatenate(
            (
                euler_from_quat(truth.quat_wxyz),
                truth.rate_frd_rad_s,
                truth.pos_ned_m,
                truth.vel_ned_m_s,
            )
        )
        x_target = np.zeros(self.NX)  # at rest on the pad
        near = float(np.linalg.norm(truth.pos_ned_m)) <= cfg.near_distance_m
        q_final = np.diag([1.0] * 6 + [10.0] * 6) * (100.0 if near else 1.0)
        r = np.diag([1.0, 100.0, 100.0, 100.0])
        x = cp.Variable((self.NX, n + 1))
        u = cp.Variable((self.NU, n))
        tilt = math.radians(cfg.max_tilt_deg)
        cost = 0
        constraints = [x[:, 0] == x0]
        for k in range(n):
            cost += cp.quad_form(u[:, k] - self.u_hover, r)
            constraints += [
                x[:, k + 1] == self.a_d @ x[:, k] + self.b_d @ (u[:, k] - self.u_hover),
                u[0, k] >= 0.0,
                u[0, k] <= cfg.max_thrust_mg * self.phys.mass * self.phys.g,
                cp.abs(u[1:4, k]) <= _MAX_TORQUE_NM,
                cp.abs(x[0:2, k + 1]) <= tilt,
                x[8, k + 1] <= 0.0,  # altitude >= 0 (NED down <= 0)
            ]
        cost += cp.quad_form(x[:, n] - x_target, q_final)
        problem = cp.Problem(cp.Minimize(cost), constraints)
        with warnings.catch_warnings():
            # CVXPY warns on "optimal_inaccurate"; the status is returned and counted instead.
            warnings.simplefilter("ignore", UserWarning)
            problem.solve(solver=cp.OSQP, warm_start=False)
        return str(problem.status)


# --------------------------------------------------------------------------- entry point


def bench_mpc(cfg: MpcBenchConfig | None = None) -> dict[str, Any]:
    """Median and p95 decision time of the MPC expert and of the paper-style baseline.

    Args:
        cfg: what to fly and time (default: :class:`MpcBenchConfig` defaults).

    Returns:
        ``median_ms``, ``p95_ms`` (our whole ``act`` call: state transform, vector update,
        OSQP), ``solver_median_ms``, ``solver_p95_ms`` (the OSQP update + solve alone),
        ``baseline_median_ms``, ``baseline_p95_ms`` (CVXPY build + OSQP solve),
        ``speedup`` (baseline median / our median), sample counts, solver stats and statuses.
    """
    cfg = cfg if cfg is not None else MpcBenchConfig()
    vehicle = load_vehicle()
    scenario = load_scenario(Path(cfg.scenario) if cfg.scenario else None)
    sim_cfg: SimConfig = load_sim().with_planet(scenario.world)
    mpc_cfg = load_mpc_config(cfg.expert_config)
    expert = MpcExpert(vehicle, sim_cfg, mpc_cfg)
    sim = Simulator(vehicle, sim_cfg, render=False)
    sampler = InitialStateSampler(scenario, cfg.seed)
    walls, solver_times, states = _fly(sim, expert, sampler, cfg)

    baseline = _PaperBaseline(Physics(vehicle, sim_cfg.planet), sim_cfg.control_dt_s, mpc_cfg)
    picks = np.linspace(0, len(states) - 1, min(cfg.baseline_samples, len(states))).astype(int)
    base_walls: list[float] = []
    statuses: dict[str, int] = {}
    for i in picks:
        t0 = time.perf_counter()
        status = baseline.solve(states[i])
        base_walls.append(time.perf_counter() - t0)
        statuses[status] = statuses.get(status, 0) + 1

    median_ms = 1e3 * statistics.median(walls)
    baseline_median_ms = 1e3 * statistics.median(base_walls)
    return {
        "benchmark": "mpc",
        "planet": scenario.world.name,
        "horizon_steps": mpc_cfg.horizon_steps,
        "samples": len(walls),
        "median_ms": median_ms,
        "p95_ms": _percentile_ms(walls, 95),
        "max_ms": 1e3 * max(walls),
        "solver_median_ms": 1e3 * statistics.median(solver_times),
        "solver_p95_ms": _percentile_ms(solver_times, 95),
        "baseline_samples": len(base_walls),
        "baseline_median_ms": baseline_median_ms,
        "baseline_p95_ms": _percentile_ms(base_walls, 95),
        "baseline_statuses": statuses,
        "speedup": baseline_median_ms / median_ms,
        "mpc_stats": {
            "solves": expert.stats.solves,
            "unsolved_osqp": expert.stats.unsolved_osqp,
            "fallback_used": expert.stats.fallback_used,
            "failed": expert.stats.failed,
        },
    }
