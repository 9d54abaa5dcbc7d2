"""Which ArduCopter flight modes need a position, and the ArduCopter parameters the SITL's
``ardupilot`` profile models (names, units and defaults as ArduCopter 4.5's; sources in
``shared/reference/mavlink_notes.md`` 1.4 and ``precland_notes.md`` 3). No I/O.

Only what changes the behaviour on the wire is here; the precision land's ``PLND_XY_DIST_MAX``,
``PLND_TIMEOUT`` and ``PLND_RET_MAX`` live in :class:`~sitl_sim.autopilot.precland.PldParams` (the
precision land the ``ardupilot`` profile reuses), ``MOT_THST_HOVER`` is
``AutopilotParams.mpc_thr_hover`` (the episode vehicle's hover thrust, as a tuned copter learns
it).
"""

from __future__ import annotations

from dataclasses import dataclass

from companion.contract.autopilots import CopterMode
from companion.table import Bounded, bounded

__all__ = [
    "GUID_OPTIONS_THRUST_AS_THRUST",
    "NEEDS_POSITION",
    "PLND_TYPE_MAVLINK",
    "ArduParams",
]

GUID_OPTIONS_THRUST_AS_THRUST = 8
"""GUID_OPTIONS bit 3: SET_ATTITUDE_TARGET's ``thrust`` is thrust, not a climb-rate demand."""
PLND_TYPE_MAVLINK = 1
"""PLND_TYPE 1: the target comes from LANDING_TARGET (a companion computer)."""


NEEDS_POSITION = frozenset(
    {
        CopterMode.AUTO,
        CopterMode.GUIDED,
        CopterMode.LOITER,
        CopterMode.RTL,
        CopterMode.CIRCLE,
        CopterMode.DRIFT,
        CopterMode.POSHOLD,
        CopterMode.BRAKE,
        CopterMode.THROW,
        CopterMode.AVOID_ADSB,
        CopterMode.SMART_RTL,
        CopterMode.FOLLOW,
        CopterMode.ZIGZAG,
        CopterMode.AUTO_RTL,
    }
)
"""Modes whose ``requires_GPS()`` is true: refused without a position estimate ("Mode change to
LOITER failed: requires position"), which this GPS-less vehicle never has."""


@dataclass(frozen=True)
class ArduParams(Bounded):
    """ArduCopter parameters (defaults as ArduCopter 4.5; units as the parameter's, converted
    in the field name where ArduPilot uses centimetres; ranges as ArduCopter's parameter
    tables, checked on construction)."""

    guid_options: int = bounded(0, 0, 2**31 - 1, name="GUID_OPTIONS")
    """GUID_OPTIONS bitmask; bit 3 (8): SET_ATTITUDE_TARGET thrust is thrust (else climb rate)."""
    guid_timeout_s: float = bounded(3.0, 0.1, 5.0, name="GUID_TIMEOUT")
    """GUID_TIMEOUT: no SET_ATTITUDE_TARGET this long in GUIDED_NOGPS -> level, zero climb."""
    fs_gcs_enable: int = bounded(0, 0, 7, name="FS_GCS_ENABLE")
    """FS_GCS_ENABLE: 0 off; any action (RTL, SmartRTL, Land, ...) lands here (no position)."""
    fs_gcs_timeout_s: float = bounded(5.0, 2.0, 120.0, name="FS_GCS_TIMEOUT")
    """FS_GCS_TIMEOUT: no HEARTBEAT from SYSID_MYGCS this long -> GCS failsafe."""
    sysid_mygcs: int = bounded(255, 1, 255, name="SYSID_MYGCS")
    """SYSID_MYGCS: the ground station whose HEARTBEAT keeps the GCS failsafe quiet."""
    wpnav_speed_up_cm_s: float = bounded(250.0, 10.0, 1000.0, name="WPNAV_SPEED_UP")
    """WPNAV_SPEED_UP: climb rate at thrust 1.0 in the climb-rate reading, cm/s."""
    wpnav_speed_dn_cm_s: float = bounded(150.0, 10.0, 500.0, name="WPNAV_SPEED_DN")
    """WPNAV_SPEED_DN: descent rate at thrust 0.0 (and LAND's upper descent), cm/s."""
    land_speed_cm_s: float = bounded(50.0, 30.0, 200.0, name="LAND_SPEED")
    """LAND_SPEED: LAND's final descent rate below LAND_ALT_LOW, cm/s."""
    land_alt_low_cm: float = bounded(1000.0, 100.0, 10000.0, name="LAND_ALT_LOW")
    """LAND_ALT_LOW: LAND descends at WPNAV_SPEED_DN above this, at LAND_SPEED below, cm."""
    disarm_delay_s: float = bounded(10.0, 0.0, 127.0, name="DISARM_DELAY")
    """DISARM_DELAY: landed this long outside LAND -> auto-disarm (0: never)."""
    plnd_enabled: int = bounded(0, 0, 1, name="PLND_ENABLED")
    """PLND_ENABLED: LAND uses the precision-land target (applies at the next LAND here)."""
    plnd_type: int = bounded(0, 0, 6, name="PLND_TYPE")
    """PLND_TYPE: 1 = MAVLink (LANDING_TARGET); any other value lands without a target."""

    @property
    def thrust_is_thrust(self) -> bool:
        return bool(self.guid_options & GUID_OPTIONS_THRUST_AS_THRUST)

    @property
    def precland(self) -> bool:
        """LAND flies the precision land (PLND_ENABLED = 1 and PLND_TYPE = MAVLink)."""
        return self.plnd_enabled == 1 and self.plnd_type == PLND_TYPE_MAVLINK
