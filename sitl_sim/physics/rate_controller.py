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
from sitl_sim.physics import kernel
from sitl_sim.physics.dynamics import Physics

__all__ = ["RateController"]


class RateController:
    """Body-rate PID with saturation and anti-windup, plus the rotor mixer.

    The loop itself is :func:`sitl_sim.physics.kernel.rate_loop`; this object holds its
    constants and its state between steps (the simulator hands both to
    :func:`sitl_sim.physics.kernel.period` for a whole control period).
    """

    def __init__(self, gains: RateControllerConfig, phys: Physics) -> None:
        self._phys = phys
        self.constants = kernel.rate_constants(gains, phys)
        """The kernel's rate-loop constants (:func:`sitl_sim.physics.kernel.rate_constants`)."""
        self.state = kernel.RATE_RESET
        """The kernel's rate-loop state: integrals, last errors, saturation."""

    @property
    def saturated(self) -> bool:
        """True when the last output was limited by the rotors."""
        return self.state[7] > 0.0

    def reset(self) -> None:
        self.state = kernel.RATE_RESET

    def setpoint(self, command: Command | None) -> tuple[bool, float, float, float, float]:
        """The kernel's view of a command: ``(armed, p, q, r, collective N)``; None is a
        disarmed autopilot (the loop reset and the rotors at zero at every step)."""
        if command is None:
            return False, 0.0, 0.0, 0.0, 0.0
        p, q, r = command.rate_frd_rad_s.tolist()
        return True, p, q, r, command.thrust_norm * self._phys.max_total_thrust_n
