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
        self._rp_xy = tuple(zip(inv[:, 1].tolist(), inv[:, 2].tolist(), strict=True))
        self._yaw = tuple(float(v) for v in inv[:, 3])
        self._max_rate = gains.max_rate_rad_s
        self._per_axis = tuple(
            zip(gains.kp, gains.ki, gains.kd, gains.integrator_limit_rad_s2, strict=True)
        )
        self.saturated = False
        """True when the last output was limited by the rotors."""

    def reset(self) -> None:
        self._integral = [0.0, 0.0, 0.0]
        self._prev_error = None
        self.saturated = False

    def update(self, command: Command, rate_frd_rad_s, dt: float) -> list[float]:
        """Rotor thrust commands (4, N, each in [0, max]) for ``command`` at measured rates.

        Plain floats, one axis at a time (the autopilot runs this at every physics step); the
        operations are those of ``J (kp e + ki int(e) + kd de/dt) + w x J w``, in that order.
        """
        phys = self._phys
        w = [float(v) for v in rate_frd_rad_s]
        integral = self._integral
        prev = self._prev_error
        err = []
        alpha = []
        for i, (v, lim, (kp, _, kd, _)) in enumerate(
            zip(command.rate_frd_rad_s.tolist(), self._max_rate, self._per_axis, strict=True)
        ):
            v = v if v < lim else lim  # the setpoint clamped: max(-lim, min(lim, v))
            e = (v if v > -lim else -lim) - w[i]
            err.append(e)
            de = e - (e if prev is None else prev[i])
            alpha.append(kp * e + integral[i] + kd * de / dt)
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
        self.saturated = limited[0] or limited[2] or collective_limited
        for i, (_, ki, _, lim) in enumerate(self._per_axis):
            if not limited[i]:
                v = integral[i] + ki * err[i] * dt
                v = v if v < lim else lim
                integral[i] = v if v > -lim else -lim
        return rotors

    def _mix(self, collective_n: float, tau) -> tuple[list[float], tuple[bool, bool, bool], bool]:
        """Allocate with priorities roll/pitch > yaw > collective.

        Returns the rotor thrusts, which torque axes were limited, and whether the collective
        had to be shifted.
        """
        tmax = self._phys.max_rotor_thrust
        tau_x, tau_y, tau_z = tau
        rp = [x * tau_x + y * tau_y for x, y in self._rp_xy]
        yw = [z * tau_z for z in self._yaw]
        limited_rp = limited_y = False
        spread = max(rp) - min(rp)
        if spread > tmax:
            k = tmax / spread
            total = [v * k + 0.0 for v in rp]  # roll/pitch scaled to fit, no yaw at all
            limited_rp = limited_y = True
        else:
            total = [a + b for a, b in zip(rp, yw)]  # noqa: B905 (4 rotors each)
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
                total = [a + b for a, b in zip(rp, yw)]  # noqa: B905
        base = collective_n / 4.0
        base_fit = min(max(base, -min(total)), tmax - max(total))
        rotors = []
        for d in total:  # min(tmax, max(0.0, base_fit + d))
            d = base_fit + d
            d = d if d > 0.0 else 0.0
            rotors.append(d if d < tmax else tmax)
        # A shifted collective protects the torque: thrust-limited, but the axes are not, so the
        # integrators keep running.
        return rotors, (limited_rp, limited_rp, limited_y), abs(base_fit - base) > 1e-9
