"""The SITL's parameter table for the MAVLink parameter protocol (PARAM_VALUE rows, which are
writable, their encoding), per autopilot profile: ``px4`` (PX4 names, INT32 byte-wise in the
float) and ``ardupilot`` (ArduCopter names, every value a plain float whatever its type, as
ArduPilot's ``PARAM_ENCODE_C_CAST``); the PARAM_* handlers in :mod:`sitl_sim.mavlink.handlers`
serve it, ``visland sitl --param`` sets it at start (:func:`parse_param_overrides`)."""

from __future__ import annotations

import math
import struct
from dataclasses import replace
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sitl_sim.autopilot.px4 import AutopilotParams

__all__ = [
    "ARDU_WRITABLE",
    "WRITABLE",
    "param_table",
    "param_value_msg",
    "parse_param_overrides",
    "with_param",
    "writable",
]

_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
_INT32 = mavlink.MAV_PARAM_TYPE_INT32
_INT16 = mavlink.MAV_PARAM_TYPE_INT16
_INT8 = mavlink.MAV_PARAM_TYPE_INT8
_INT_TYPES = (_INT8, _INT16, _INT32)

WRITABLE: dict[str, tuple[str | None, str, int]] = {
    "COM_OF_LOSS_T": (None, "com_of_loss_t_s", _REAL32),
    "COM_DISARM_LAND": (None, "com_disarm_land_s", _REAL32),
    "PLD_BTOUT": ("pld", "btout_s", _REAL32),
    "PLD_HACC_RAD": ("pld", "hacc_rad_m", _REAL32),
    "PLD_FAPPR_ALT": ("pld", "fappr_alt_m", _REAL32),
    "PLD_SRCH_ALT": ("pld", "srch_alt_m", _REAL32),
    "PLD_SRCH_TOUT": ("pld", "srch_tout_s", _REAL32),
    "PLD_MAX_SRCH": ("pld", "max_srch", _INT32),
    "LTEST_MODE": ("ltest", "mode", _INT32),
    "LTEST_ACC_UNC": ("ltest", "acc_unc", _REAL32),
    "LTEST_MEAS_UNC": ("ltest", "meas_unc", _REAL32),
    "LTEST_POS_UNC_IN": ("ltest", "pos_unc_in", _REAL32),
    "LTEST_VEL_UNC_IN": ("ltest", "vel_unc_in", _REAL32),
}
"""Parameters a PARAM_SET changes (name -> (AutopilotParams group or None, field, type)); any
other PARAM_SET is answered with the unchanged value (the protocol's way of saying no). A
precision-land parameter set during AUTO.PRECLAND applies from the next activation."""


ARDU_WRITABLE: dict[str, tuple[str | None, str, int]] = {
    "DISARM_DELAY": ("ardu", "disarm_delay_s", _INT8),
    "FS_GCS_ENABLE": ("ardu", "fs_gcs_enable", _INT8),
    "FS_GCS_TIMEOUT": ("ardu", "fs_gcs_timeout_s", _REAL32),
    "GUID_OPTIONS": ("ardu", "guid_options", _INT32),
    "GUID_TIMEOUT": ("ardu", "guid_timeout_s", _REAL32),
    "LAND_ALT_LOW": ("ardu", "land_alt_low_cm", _INT16),
    "LAND_SPEED": ("ardu", "land_speed_cm_s", _INT16),
    "PLND_ENABLED": ("ardu", "plnd_enabled", _INT8),
    "PLND_RET_MAX": ("pld", "max_srch", _INT8),
    "PLND_TIMEOUT": ("pld", "btout_s", _REAL32),
    "PLND_TYPE": ("ardu", "plnd_type", _INT8),
    "PLND_XY_DIST_MAX": ("pld", "hacc_rad_m", _REAL32),
    "SYSID_MYGCS": ("ardu", "sysid_mygcs", _INT16),
    "WPNAV_SPEED_DN": ("ardu", "wpnav_speed_dn_cm_s", _REAL32),
    "WPNAV_SPEED_UP": ("ardu", "wpnav_speed_up_cm_s", _REAL32),
}
"""The ``ardupilot`` profile's writable parameters (ArduCopter names and types). The precision
land's PLND_XY_DIST_MAX, PLND_TIMEOUT and PLND_RET_MAX drive the reused PX4-style precision
land as its PLD_HACC_RAD, PLD_BTOUT and PLD_MAX_SRCH (sitl_sim/autopilot/ardupilot.py)."""


def writable(profile: str = "px4") -> dict[str, tuple[str | None, str, int]]:
    """The writable parameters of an autopilot profile."""
    return ARDU_WRITABLE if profile == "ardupilot" else WRITABLE


def param_table(
    params: AutopilotParams, sysid: int, profile: str = "px4"
) -> list[tuple[str, float, int]]:
    """``(name, value, MAV_PARAM_TYPE)`` rows, in PARAM_VALUE index order."""
    p = params
    if profile == "ardupilot":
        rows = [
            (name, _value(p, group, field), t) for name, (group, field, t) in ARDU_WRITABLE.items()
        ]
        rows += [
            ("MOT_THST_HOVER", p.mpc_thr_hover, _REAL32),  # read-only: the vehicle's
            ("SYSID_THISMAV", sysid, _INT16),
        ]
        return sorted(rows)  # ArduPilot lists them by name
    rows = [
        ("COM_OF_LOSS_T", p.com_of_loss_t_s, _REAL32),
        ("COM_OBL_RC_ACT", p.com_obl_rc_act, _INT32),
        ("COM_DISARM_LAND", p.com_disarm_land_s, _REAL32),
        ("MPC_THR_HOVER", p.mpc_thr_hover, _REAL32),
        ("MAV_SYS_ID", sysid, _INT32),
    ]
    for name, (group, field, ptype) in WRITABLE.items():
        if group is not None:
            rows.append((name, getattr(getattr(p, group), field), ptype))
    rows.append(("RTL_PLD_MD", 0, _INT32))  # RTL is not modelled: precision RTL off (PX4 default)
    return rows


def _value(params: AutopilotParams, group: str | None, field: str) -> float:
    holder = params if group is None else getattr(params, group)
    return getattr(holder, field)


def param_value_msg(
    mav: Any, table: list[tuple[str, float, int]], index: int, profile: str = "px4"
) -> Any:
    """PARAM_VALUE of row ``index`` of ``table``, encoded with ``mav`` (PX4: INT32 byte-wise;
    ArduPilot: every value as a float)."""
    name, value, ptype = table[index]
    if ptype == _INT32 and profile == "px4":
        wire = _float_bits_of_int(int(value))
    else:
        wire = float(value)
    return mav.param_value_encode(name.encode(), wire, ptype, len(table), index)


def with_param(
    params: AutopilotParams, name: str, value: float, profile: str = "px4"
) -> AutopilotParams:
    """``params`` with the writable parameter ``name`` set to ``value`` (a PARAM_SET's float).
    PX4: an INT32 byte-wise, as QGroundControl/MAVSDK set it, or as an integral float.
    ArduPilot: an integer parameter is the float + 0.01 truncated, as ``AP_Param::set_float``.

    Raises:
        KeyError: ``name`` is not writable in this profile.
        ValueError: the parameter group rejects the value.
    """
    group, field, ptype = writable(profile)[name]
    new: float | int
    if profile == "ardupilot":
        new = _ap_int(value) if ptype in _INT_TYPES else float(value)
    else:
        new = _int_of_float_bits(value) if ptype == _INT32 else float(value)
    if group is None:
        return replace(params, **{field: new})
    return replace(params, **{group: replace(getattr(params, group), **{field: new})})


def _float_bits_of_int(value: int) -> float:
    """PX4 sends INT32 parameters byte-wise inside the float field (PARAM_ENCODE_BYTEWISE)."""
    return struct.unpack("<f", struct.pack("<i", int(value)))[0]


def _int_of_float_bits(value: float) -> int:
    """The INT32 a PARAM_SET carries: byte-wise in the float field (PX4, MAVSDK), or — from a
    client that casts (pymavlink scripts) — as an integral float; a small integer's bytes are a
    denormal, never integral, so the two cannot be confused."""
    value = float(value)
    if value == int(value) and abs(value) < 2**24:
        return int(value)
    return struct.unpack("<i", struct.pack("<f", value))[0]


def _ap_int(value: float) -> int:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"non-finite value {value} for an integer parameter")
    return int(value + (0.01 if value >= 0 else -0.01))


def parse_param_overrides(text: str | None, profile: str = "px4") -> list[tuple[str, float]]:
    """``NAME=VALUE[,NAME=VALUE...]`` (``visland sitl --param``) -> ``[(name, value)]``,
    checked against the profile's writable parameters (the values are checked when applied).

    Raises:
        ValueError: a malformed item or a name that is not writable (names the known ones).
    """
    out: list[tuple[str, float]] = []
    if not text:
        return out
    known = writable(profile)
    for item in text.split(","):
        name, sep, raw = item.strip().partition("=")
        name = name.strip().upper()
        if not sep or not name:
            raise ValueError(f"--param item {item!r}: expected NAME=VALUE")
        if name not in known:
            raise ValueError(
                f"--param {name}: not a writable {profile} parameter; known: {sorted(known)}"
            )
        try:
            value = float(raw)
        except ValueError:
            raise ValueError(f"--param {name}={raw!r}: expected a number") from None
        out.append((name, value))
    return out
