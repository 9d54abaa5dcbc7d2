"""Unsigned MAVLink 2 frames packed without pymavlink's per-message header object.

pymavlink's ``msg.pack(mav)`` builds a header object, a bytearray and a CRC object for every
frame (~8 us); the SITL packs ~170 frames a simulated second. :func:`pack_unsigned` writes the
same bytes — the payload through the message class's own ``struct`` (fields in wire order,
arrays element by element, text fields as one value), trailing zero bytes cut as MAVLink 2 does
(at least one byte kept), the header, the CRC-16/MCRF4XX over header, payload and the message's
CRC extra — in a third of the time. Signed frames stay pymavlink's (``msg.pack``). The test
packs every message of the dialect both ways.
"""

from __future__ import annotations

import operator
import struct
from collections.abc import Callable
from typing import Any

from pymavlink.generator import mavcrc

__all__ = ["pack_unsigned"]

_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")


def _crc_python(data: bytes, crc: int) -> int:  # pragma: no cover - without fastcrc
    acc = mavcrc.x25crc()
    acc.crc = crc
    acc.accumulate(data)
    return acc.crc


_mcrf4xx = mavcrc.mcrf4xx or _crc_python
"""CRC-16/MCRF4XX: the C one pymavlink itself uses (``fastcrc``) when it is installed."""


_Layout = tuple[Callable[[Any], tuple[Any, ...]], Callable[..., bytes], bytes, int, int]
_LAYOUTS: dict[type, _Layout] = {}


def _layout(msg: Any) -> _Layout:
    """(wire values of a message, its payload packer, its CRC extra byte, message id low 16
    bits, high 8 bits) of a dialect message's class. A text field is packed from its bytes as
    given (pymavlink keeps them as ``_<name>_raw`` beside the decoded ``<name>``)."""
    cls = type(msg)
    types = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
    names = [
        f"_{name}_raw" if types[name] == "char" and hasattr(msg, f"_{name}_raw") else name
        for name in cls.ordered_fieldnames
    ]
    counts = [
        n if n and types[name] != "char" else 0
        for name, n in zip(cls.ordered_fieldnames, cls.array_lengths, strict=True)
    ]
    getter = operator.attrgetter(*names)
    if len(names) == 1:

        def raw(msg: Any) -> tuple[Any, ...]:
            return (getter(msg),)
    else:
        raw = getter
    if not any(counts):
        values = raw
    else:

        def values(msg: Any) -> tuple[Any, ...]:
            out: list[Any] = []
            for value, n in zip(raw(msg), counts, strict=True):
                if n:
                    out.extend(value[:n])  # the array's first n elements (pack indexes them)
                else:
                    out.append(value)
            return tuple(out)

    msg_id = cls.id
    layout = (values, cls.unpacker.pack, bytes((cls.crc_extra,)), msg_id & 0xFFFF, msg_id >> 16)
    _LAYOUTS[cls] = layout
    return layout


def pack_unsigned(msg: Any, seq: int, system: int, component: int) -> bytes:
    """``msg`` as the unsigned MAVLink 2 frame ``msg.pack(mav)`` gives for a codec ``mav``
    with that sequence number, system and component (and signing off)."""
    layout = _LAYOUTS.get(type(msg)) or _layout(msg)
    values, pack, crc_extra, id_low, id_high = layout
    payload = pack(*values(msg))
    cut = payload.rstrip(b"\x00") or payload[:1]
    header = _HEADER.pack(253, len(cut), 0, 0, seq, system, component, id_low, id_high)
    crc = _mcrf4xx(header[1:] + cut + crc_extra, 0xFFFF)
    return header + cut + _CRC.pack(crc)
