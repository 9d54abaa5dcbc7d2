"""The autopilot's inner loop: body-rate PID + quad-X mixer, as PX4's mc_rate_control.

It turns a :class:`companion.contract.Command` (collective thrust fraction and FRD body rates) into
four rotor thrust commands. Gains are angular accelerations per rate error, so the torque is
``J * (kp e + ki int(e) + kd de/dt) + w x J w`` (the gyroscopic term is fed forward).

Saturation is handled as PX4's mixer does: roll/pitch torque has priority over yaw torque, which
has priority over collective thrust; the collective is shifted to fit the torque into the rotor
range. Whenever an axis is limited, its integrator is frozen (anti-windup by conditional
integration) and the integral is always clamped to ``integrator_limit_rad_s2``.
"""

from __future__ import annotations

from companion.contract import Command
from sitl_sim.config import RateControllerConfig
from sitl_sim.physics.dynamics import Physics

__all__ = ["RateController"]


class RateController:
    """Body-rate PID with saturation and anti-windup, plus the rotor mixer."""

    def __init__(self, gains: RateControllerConfig, phys: Physics) -> None:
        self._gains = gains
        self._phys = phys
        self._integral = [0.0, 0.0, 0.0]
        self._prev_error: list[float] | None = None
        inv = phys.allocation_inv
        # Per-rotor thrust per unit torque (columns 1..3 of the inverse allocation), as floats.
        self._rp_x = tuple(float(v) for v in inv[:, 1])
        self._rp_y = tuple(float(v) for v in inv[:, 2])
        self._yaw = tuple(float(v) for v in inv[:, 3])
        self.saturated = False
        """True when the last output was limited by the rotors."""

    def reset(self) -> None:
        self._integral = [0.0, 0.0, 0.0]
        self._prev_error = None
        self.saturated = False

    def update(self, command: Command, rate_frd_rad_s, dt: float) -> list[float]:
        """Rotor thrust commands (4, N, each in [0, max]) for ``command`` at measured rates."""
        g = self._gains
        phys = self._phys
        sp = [
            max(-lim, min(lim, float(v)))
            for v, lim in zip(command.rate_frd_rad_s, g.max_rate_rad_s, strict=True)
        ]
        w = [float(v) for v in rate_frd_rad_s]
        err = [sp[i] - w[i] for i in range(3)]
        prev = self._prev_error if self._prev_error is not None else err
        alpha = [
            g.kp[i] * err[i] + self._integral[i] + g.kd[i] * (err[i] - prev[i]) / dt
            for i in range(3)
        ]
        self._prev_error = err
        ixx, iyy, izz = phys.ixx, phys.iyy, phys.izz
        p, q, r = w
        # tau = J alpha + w x (J w)
        tau = (
            ixx * alpha[0] + (izz - iyy) * q * r,
            iyy * alpha[1] + (ixx - izz) * r * p,
            izz * alpha[2] + (iyy - ixx) * p * q,
        )
        collective = command.thrust_norm * phys.max_total_thrust_n
        rotors, limited, collective_limited = self._mix(collective, tau)
        self.saturated = any(limited) or collective_limited
        for i in range(3):
            if not limited[i]:
                lim = g.integrator_limit_rad_s2[i]
                self._integral[i] = max(-lim, min(lim, self._integral[i] + g.ki[i] * err[i] * dt))
        return rotors

    def _mix(self, collective_n: float, tau) -> tuple[list[float], tuple[bool, bool, bool], bool]:
        """Allocate with priorities roll/pitch > yaw > collective.

        Returns the rotor thrusts, which torque axes were limited, and whether the collective
        had to be shifted.
        """
        tmax = self._phys.max_rotor_thrust
        rx, ry, yz = self._rp_x, self._rp_y, self._yaw
        rp = [rx[i] * tau[0] + ry[i] * tau[1] for i in range(4)]
        yw = [yz[i] * tau[2] for i in range(4)]
        limited_rp = limited_y = False
        spread = max(rp) - min(rp)
        if spread > tmax:
            k = tmax / spread
            rp = [v * k for v in rp]
            yw = [0.0] * 4
            limited_rp = limited_y = True
        else:
            total = [rp[i] + yw[i] for i in range(4)]
            if max(total) - min(total) > tmax:
                # Largest yaw fraction that still fits: spread is piecewise linear in the fraction.
                lo, hi = 0.0, 1.0
                for _ in range(20):
                    mid = 0.5 * (lo + hi)
                    t = [rp[i] + mid * yw[i] for i in range(4)]
                    if max(t) - min(t) > tmax:
                        hi = mid
                    else:
                        lo = mid
                yw = [v * lo for v in yw]
                limited_y = True
        delta = [rp[i] + yw[i] for i in range(4)]
        base = collective_n / 4.0
        base_fit = min(max(base, -min(delta)), tmax - max(delta))
        rotors = [min(tmax, max(0.0, base_fit + d)) for d in delta]
        # A shifted collective protects the torque: thrust-limited, but the axes are not, so the
        # integrators keep running.
        return rotors, (limited_rp, limited_rp, limited_y), abs(base_fit - base) > 1e-9
