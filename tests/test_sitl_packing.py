"""The SITL's own MAVLink 2 packing gives pymavlink's bytes for every message of the dialect."""

from __future__ import annotations

import random

from pymavlink.dialects.v20 import common as mavlink

from sitl_sim.mavlink.packing import pack_unsigned


def _value(rng: random.Random, kind: str):
    if kind in ("float", "double"):
        return rng.choice([0.0, -0.0, rng.uniform(-1e3, 1e3), float("nan"), float("inf")])
    bits = int("".join(ch for ch in kind if ch.isdigit()))
    if kind.startswith("u"):
        return rng.choice([0, rng.randrange(2**bits)])
    return rng.choice([0, rng.randrange(-(2 ** (bits - 1)), 2 ** (bits - 1))])


def test_every_message_packs_to_pymavlinks_frame():
    """Random fields (zeros that MAVLink 2 cuts off the payload's end, NaN, text, arrays), any
    sequence number, system and component: the frame of ``msg.pack(mav)``, byte for byte."""
    rng = random.Random(0)
    for cls in mavlink.mavlink_map.values():
        kinds = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
        lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
        for _ in range(10):
            fields = []
            for name in cls.fieldnames:
                kind, n = kinds[name], lengths[name]
                if kind == "char":
                    fields.append(bytes(rng.choice(b"ab \x00") for _ in range(rng.randint(0, n))))
                elif n:
                    fields.append([_value(rng, kind) for _ in range(n)])
                else:
                    fields.append(_value(rng, kind))
            msg = cls(*fields)
            system, component, seq = (rng.randrange(256) for _ in range(3))
            mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=component)
            mav.seq = seq
            frame = pack_unsigned(msg, seq, system, component)
            assert frame == msg.pack(mav), cls.msgname
