"""What several parts of the MAVLink SITL read during a flight, and which part changes it.

The SITL (:class:`~sitl_sim.mavlink.sitl.MavlinkSitl`) is composed of parts that each own their
own state; the little they share is this one object, passed to each part that needs it, with
the part that writes each field named below.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sitl_sim.autopilot.px4 import Autopilot, LandController
    from sitl_sim.mavlink.clock import FrameWait
    from sitl_sim.simulator import Simulator

__all__ = ["FlightState"]


@dataclass
class FlightState:
    """The flight's shared state.

    Attributes:
        autopilot: the autopilot profile flying this episode (a fresh one per episode:
            :class:`~sitl_sim.mavlink.episodes.Episodes`); its ``params`` are the parameter
            table (PARAM_SET: :class:`~sitl_sim.mavlink.handlers.Handlers`).
        land_controller: AUTO.LAND's (and the precision land's) controller, tuned for the
            episode's airframe (:class:`~sitl_sim.mavlink.episodes.Episodes`).
        flying: the take-over happened and the flight runs (Episodes).
        wait: in lockstep, the camera frame the clock waits on (set by the loop, answered by
            the handlers and the precision land).
        offboard_paced: in lockstep, OFFBOARD frames wait for the client's answer (False after
            an unanswered frame, for an autopilot that ``runs_free_when_unanswered``, until it
            answers again: the loop clears it, the SET_ATTITUDE_TARGET handler sets it).
        frame_id: the next camera frame's id (the loop).
        lockstep_timeouts: frames the client left unanswered past ``lockstep_timeout_s`` (the
            loop; SYS_STATUS and the episode result report it).
    """

    autopilot: Autopilot
    land_controller: LandController
    flying: bool = False
    wait: FrameWait | None = None
    offboard_paced: bool = True
    frame_id: int = 0
    lockstep_timeouts: int = 0

    def on_ground(self, sim: Simulator) -> bool:
        """In flight and on the ground (:meth:`Simulator.on_ground`: within 1 cm of the plane,
        or resting on a site's surface): the land detector's input."""
        return self.flying and sim.on_ground()
