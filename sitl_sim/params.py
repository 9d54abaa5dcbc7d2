"""The SITL's parameter table for the MAVLink parameter protocol (PARAM_VALUE rows, which are
writable, PX4's byte-wise INT32 encoding); the PARAM_* handlers in
:mod:`sitl_sim.mavlink_handlers` serve it."""

from __future__ import annotations

import struct
from dataclasses import replace
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sitl_sim.autopilot import AutopilotParams

__all__ = ["WRITABLE", "param_table", "param_value_msg", "with_param"]

_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
_INT32 = mavlink.MAV_PARAM_TYPE_INT32

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


def param_table(params: AutopilotParams, sysid: int) -> list[tuple[str, float, int]]:
    """``(name, value, MAV_PARAM_TYPE)`` rows, in PARAM_VALUE index order."""
    p = params
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


def param_value_msg(mav: Any, table: list[tuple[str, float, int]], index: int) -> Any:
    """PARAM_VALUE of row ``index`` of ``table``, encoded with ``mav``."""
    name, value, ptype = table[index]
    wire = _float_bits_of_int(int(value)) if ptype == _INT32 else value
    return mav.param_value_encode(name.encode(), wire, ptype, len(table), index)


def with_param(params: AutopilotParams, name: str, value: float) -> AutopilotParams:
    """``params`` with the writable parameter ``name`` set to ``value`` (a PARAM_SET's float;
    an INT32 one byte-wise, as QGroundControl/MAVSDK set it, or as an integral float).

    Raises:
        KeyError: ``name`` is not in :data:`WRITABLE`.
        ValueError: the parameter group rejects the value.
    """
    group, field, ptype = WRITABLE[name]
    new: float | int = _int_of_float_bits(value) if ptype == _INT32 else float(value)
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
