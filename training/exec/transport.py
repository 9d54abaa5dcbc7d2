"""How a flight reaches the simulator: one name for it everywhere (eval, fly, DAgger rollouts).

``inprocess``: the simulator runs in the evaluating process (or its worker processes), the
policy is called directly. ``mavlink``: ``visland sitl`` and ``visland companion`` run as two
processes talking MAVLink 2 over UDP in lockstep (``visland fly``). Both fly the same physics;
a report's ``transport`` key holds the value.
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["Transport"]


class Transport(StrEnum):
    """The transport of a flight (the values are the CLI choices and the JSON strings)."""

    INPROCESS = "inprocess"
    MAVLINK = "mavlink"
