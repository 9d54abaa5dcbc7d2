"""A cascaded PD lander on privileged state: the simple baseline controller, as a Policy.

The controller itself is the SITL autopilot's AUTO.LAND controller,
:class:`sitl_sim.autopilot.land_controller.CascadeLandController` (one implementation: the
SITL's LAND mode and this baseline fly the same law). This module adds the
:class:`companion.contract.policy.Policy` interface. It reads ground truth, so it is a
*privileged* controller — the scripted pilot of the demo and of the simulator benchmarks, and
the reference the MPC expert must beat.
"""

from __future__ import annotations

from companion.contract import MissingGroundTruthError
from sitl_sim.autopilot.land_controller import CascadeGains, CascadeLandController

__all__ = ["CascadeGains", "CascadeLander"]


class CascadeLander(CascadeLandController):
    """Ground truth in, Command out: ``command(pos, vel, quat) -> Command``.

    Also a (privileged, stateless) :class:`companion.contract.policy.Policy`.
    """

    privileged = True

    def initial_state(self) -> None:
        return None

    def act(self, observation, groundtruth, state):
        """The Policy interface: needs ``groundtruth`` (privileged)."""
        if groundtruth is None:
            raise MissingGroundTruthError("CascadeLander is privileged: act() needs groundtruth")
        gt = groundtruth
        return self.command(gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz), state
