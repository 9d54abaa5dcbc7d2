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

WRITABLE = {"COM_OF_LOSS_T": "com_of_loss_t_s", "COM_DISARM_LAND": "com_disarm_land_s"}
"""Parameters a PARAM_SET changes (name -> AutopilotParams field); any other PARAM_SET is
answered with the unchanged value (the protocol's way of saying no)."""


def param_table(params: AutopilotParams, sysid: int) -> list[tuple[str, float, int]]:
    """``(name, value, MAV_PARAM_TYPE)`` rows, in PARAM_VALUE index order."""
    p = params
    return [
        ("COM_OF_LOSS_T", p.com_of_loss_t_s, mavlink.MAV_PARAM_TYPE_REAL32),
        ("COM_OBL_RC_ACT", p.com_obl_rc_act, mavlink.MAV_PARAM_TYPE_INT32),
        ("COM_DISARM_LAND", p.com_disarm_land_s, mavlink.MAV_PARAM_TYPE_REAL32),
        ("MPC_THR_HOVER", p.mpc_thr_hover, mavlink.MAV_PARAM_TYPE_REAL32),
        ("MAV_SYS_ID", sysid, mavlink.MAV_PARAM_TYPE_INT32),
    ]


def param_value_msg(mav: Any, table: list[tuple[str, float, int]], index: int) -> Any:
    """PARAM_VALUE of row ``index`` of ``table``, encoded with ``mav``."""
    name, value, ptype = table[index]
    wire = _float_bits_of_int(int(value)) if ptype == mavlink.MAV_PARAM_TYPE_INT32 else value
    return mav.param_value_encode(name.encode(), wire, ptype, len(table), index)


def with_param(params: AutopilotParams, name: str, value: float) -> AutopilotParams:
    """``params`` with the writable parameter ``name`` set to ``value``.

    Raises:
        KeyError: ``name`` is not in :data:`WRITABLE`.
        ValueError: AutopilotParams rejects the value.
    """
    return replace(params, **{WRITABLE[name]: float(value)})


def _float_bits_of_int(value: int) -> float:
    """PX4 sends INT32 parameters byte-wise inside the float field (PARAM_ENCODE_BYTEWISE)."""
    return struct.unpack("<f", struct.pack("<i", int(value)))[0]
