"""The autopilots visland flies with, as one table: mode numbers, parameters, arming rules.

Both ends of the MAVLink link read it: the companion's link (which mode to request, what a
HEARTBEAT's ``custom_mode`` means, which parameter holds the hover thrust) and the SITL's
autopilot profiles (:mod:`sitl_sim.autopilot.px4` is the ``px4`` one,
:mod:`sitl_sim.autopilot.ardupilot` the
``ardupilot`` one: which numbers they show and accept). A mode number is written here once.

* **PX4** ``custom_mode = (main << 16) | (sub << 24)`` (``px4_custom_mode.h``):
  :class:`Px4MainMode`, and the (main, sub) pairs visland names in :class:`Px4Mode`.
* **ArduCopter** ``custom_mode`` is ``Mode::Number`` itself: :class:`CopterMode`.
* :class:`AutopilotProfile` (:data:`PX4`, :data:`ARDUPILOT`, by name in :data:`PROFILES`): what
  differs between the two for an offboard rate controller.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Protocol

from pymavlink.dialects.v20 import common as mavlink

__all__ = [
    "ARDUPILOT",
    "FORCE_DISARM_MAGIC",
    "PROFILES",
    "PX4",
    "PX4_AUTO_SUB_MODES",
    "AutopilotMode",
    "AutopilotProfile",
    "CopterMode",
    "Px4MainMode",
    "Px4Mode",
]

FORCE_DISARM_MAGIC = 21196.0
"""MAV_CMD_COMPONENT_ARM_DISARM param2 that forces a disarm in the air (PX4, ArduPilot)."""


class Px4MainMode(enum.IntEnum):
    """PX4 main modes (``PX4_CUSTOM_MAIN_MODE_*``): byte 2 of ``custom_mode``."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8
    SIMPLE = 9
    TERMINATION = 10
    ALTITUDE_CRUISE = 11


PX4_AUTO_SUB_MODES = range(1, 19)
"""PX4 AUTO sub modes (byte 3 of ``custom_mode``), READY (1) .. EXTERNAL8 (18)."""


class Px4Mode(enum.Enum):
    """The PX4 modes visland names, valued by (main_mode, sub_mode)."""

    MANUAL = (1, 0)
    ALTCTL = (2, 0)
    POSCTL = (3, 0)
    AUTO_LOITER = (4, 3)  # shown as "Hold"
    AUTO_RTL = (4, 5)
    AUTO_LAND = (4, 6)
    AUTO_PRECLAND = (4, 9)
    OFFBOARD = (6, 0)  # no sub mode: any sub is OFFBOARD
    STABILIZED = (7, 0)

    @property
    def custom_mode(self) -> int:
        """The HEARTBEAT ``custom_mode`` (e.g. OFFBOARD = 393216)."""
        main, sub = self.value
        return (main << 16) | (sub << 24)

    @property
    def set_mode_args(self) -> tuple[float, float]:
        """DO_SET_MODE param2, param3: main mode, sub mode."""
        main, sub = self.value
        return float(main), float(sub)

    @property
    def label(self) -> str:
        """PX4's name (``AUTO.LOITER``)."""
        return self.name.replace("_", ".")

    @classmethod
    def from_main_sub(cls, main: int, sub: int) -> Px4Mode | None:
        """The mode of a (main, sub) pair (None: not one named here)."""
        if main == Px4MainMode.OFFBOARD:
            return cls.OFFBOARD
        try:
            return cls((main, sub))
        except ValueError:
            return None

    @classmethod
    def from_custom(cls, custom_mode: int) -> Px4Mode | None:
        """The mode of a HEARTBEAT ``custom_mode`` (None: not one named here)."""
        return cls.from_main_sub((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)

    @classmethod
    def name_of(cls, custom_mode: int) -> str:
        """The label of a ``custom_mode``, or ``PX4 main/sub``."""
        mode = cls.from_custom(custom_mode)
        if mode is not None:
            return mode.label
        return f"PX4 {(custom_mode >> 16) & 0xFF}/{(custom_mode >> 24) & 0xFF}"


class CopterMode(enum.IntEnum):
    """ArduCopter ``Mode::Number`` (the HEARTBEAT ``custom_mode``)."""

    STABILIZE = 0
    ACRO = 1
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    CIRCLE = 7
    LAND = 9
    DRIFT = 11
    SPORT = 13
    FLIP = 14
    AUTOTUNE = 15
    POSHOLD = 16
    BRAKE = 17
    THROW = 18
    AVOID_ADSB = 19
    GUIDED_NOGPS = 20
    SMART_RTL = 21
    FLOWHOLD = 22
    FOLLOW = 23
    ZIGZAG = 24
    SYSTEMID = 25
    AUTOROTATE = 26
    AUTO_RTL = 27
    TURTLE = 28

    @property
    def custom_mode(self) -> int:
        """The HEARTBEAT ``custom_mode``: the number itself."""
        return int(self)

    @property
    def set_mode_args(self) -> tuple[float, float]:
        """DO_SET_MODE param2, param3: the number, 0."""
        return float(self), 0.0

    @property
    def label(self) -> str:
        """ArduCopter's name (``GUIDED_NOGPS``)."""
        return self.name

    @classmethod
    def from_custom(cls, custom_mode: int) -> CopterMode | None:
        """The mode of a HEARTBEAT ``custom_mode`` (None: no such mode)."""
        try:
            return cls(custom_mode)
        except ValueError:
            return None

    @classmethod
    def name_of(cls, custom_mode: int) -> str:
        """The name of a ``custom_mode``, or ``ArduPilot N``."""
        mode = cls.from_custom(custom_mode)
        return mode.label if mode is not None else f"ArduPilot {custom_mode}"


class AutopilotMode(Protocol):
    """A mode of either table (:class:`Px4Mode`, :class:`CopterMode`)."""

    @property
    def custom_mode(self) -> int: ...

    @property
    def set_mode_args(self) -> tuple[float, float]: ...

    @property
    def label(self) -> str: ...


@dataclass(frozen=True)
class AutopilotProfile:
    """What differs between autopilots for an offboard rate controller.

    Attributes:
        name: ``px4`` or ``ardupilot``.
        mav_autopilot: the HEARTBEAT's ``autopilot`` (MAV_AUTOPILOT_PX4 12, ARDUPILOTMEGA 3).
        modes: the table of its mode numbers (:class:`Px4Mode` or :class:`CopterMode`).
        offboard: the mode that takes SET_ATTITUDE_TARGET (PX4 OFFBOARD; ArduPilot
            GUIDED_NOGPS).
        land: the landing mode (PX4 AUTO.LAND; ArduPilot LAND).
        hold: the hand-back hold mode (PX4 AUTO.LOITER; ArduPilot ALT_HOLD: LOITER needs a
            position estimate, which a GPS-less vehicle lacks).
        hover_param: the parameter holding the hover thrust (PX4 MPC_THR_HOVER, ArduPilot
            MOT_THST_HOVER).
        thrust_param: a parameter that must have ``thrust_param_bits`` set for ``thrust`` to be
            collective thrust, or None when it always is (PX4). ArduPilot reads ``thrust`` as a
            climb-rate demand (0.5 = hold altitude) unless GUID_OPTIONS bit 3 (8) is set.
        precland: the mode that lands on LANDING_TARGET (PX4 AUTO.PRECLAND; ArduPilot LAND,
            which uses the target when PLND_ENABLED = 1).
        landing_target_position: send LANDING_TARGET's x, y, z with ``position_valid = 1`` in
            MAV_FRAME_BODY_FRD (ArduPilot reads them, divided by ``distance``); PX4 drops a
            body-frame position outright ("coordinate frame 12 unsupported"), so for PX4 the
            angle form alone is sent.
        precland_param: a parameter that must be 1 for the precision land to use the target
            (ArduPilot PLND_ENABLED), or None (PX4: AUTO.PRECLAND always does).
    """

    name: str
    mav_autopilot: int
    modes: type[Px4Mode] | type[CopterMode]
    offboard: AutopilotMode
    land: AutopilotMode
    hold: AutopilotMode
    hover_param: str
    precland: AutopilotMode
    thrust_param: str | None = None
    thrust_param_bits: int = 0
    landing_target_position: bool = False
    precland_param: str | None = None

    def mode_of(self, custom_mode: int) -> AutopilotMode | None:
        """The mode a HEARTBEAT ``custom_mode`` shows (None: not one in the table)."""
        return self.modes.from_custom(custom_mode)

    def is_offboard(self, custom_mode: int) -> bool:
        return self.mode_of(custom_mode) == self.offboard

    def is_land(self, custom_mode: int) -> bool:
        """The landing mode or the precision land (PX4 AUTO.LAND or AUTO.PRECLAND)."""
        return self.mode_of(custom_mode) in (self.land, self.precland)

    def is_precland(self, custom_mode: int) -> bool:
        return self.mode_of(custom_mode) == self.precland

    def is_hold(self, custom_mode: int) -> bool:
        return self.mode_of(custom_mode) == self.hold

    def mode_name(self, custom_mode: int) -> str:
        """The autopilot's name of a ``custom_mode`` (its number where it has none here)."""
        return self.modes.name_of(custom_mode)

    def set_mode_params(self, mode: AutopilotMode, armed: bool) -> tuple[float, float, float]:
        """DO_SET_MODE param1..3 (param1 = CUSTOM_MODE_ENABLED, + SAFETY_ARMED when armed)."""
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
        )
        return (float(base), *mode.set_mode_args)


PX4 = AutopilotProfile(
    name="px4",
    mav_autopilot=mavlink.MAV_AUTOPILOT_PX4,
    modes=Px4Mode,
    offboard=Px4Mode.OFFBOARD,
    land=Px4Mode.AUTO_LAND,
    hold=Px4Mode.AUTO_LOITER,
    hover_param="MPC_THR_HOVER",
    precland=Px4Mode.AUTO_PRECLAND,
)
ARDUPILOT = AutopilotProfile(
    name="ardupilot",
    mav_autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    modes=CopterMode,
    offboard=CopterMode.GUIDED_NOGPS,
    land=CopterMode.LAND,
    hold=CopterMode.ALT_HOLD,
    hover_param="MOT_THST_HOVER",
    precland=CopterMode.LAND,
    thrust_param="GUID_OPTIONS",
    thrust_param_bits=8,
    landing_target_position=True,
    precland_param="PLND_ENABLED",
)
PROFILES = {"px4": PX4, "ardupilot": ARDUPILOT}
"""The profiles by name (the companion's ``autopilot``, the SITL's ``--autopilot``)."""
