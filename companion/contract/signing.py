"""MAVLink 2 message signing as both ends of a visland link apply it.

One parser for the secret (``visland sitl --signing-key`` and the companion's ``signing_key``
take the same text), PX4's list of messages accepted unsigned on a signed link, the signing
clock both ends stamp with, and the set-up that signs what a pymavlink encoder sends.
"""

from __future__ import annotations

import hashlib
import string
import time
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

__all__ = [
    "SIGNING_EPOCH_UNIX_S",
    "UNSIGNED_ALLOWED",
    "SigningKeyError",
    "sign_outgoing",
    "signing_key_bytes",
    "signing_timestamp_now",
]

SIGNING_EPOCH_UNIX_S = 1_420_070_400
"""The MAVLink 2 signing epoch, 2015-01-01 00:00:00 UTC, in Unix seconds (MAVLink message
signing spec, "Timestamp")."""

UNSIGNED_ALLOWED = frozenset(
    {
        mavlink.MAVLINK_MSG_ID_HEARTBEAT,
        mavlink.MAVLINK_MSG_ID_RADIO_STATUS,
        mavlink.MAVLINK_MSG_ID_ADSB_VEHICLE,
        mavlink.MAVLINK_MSG_ID_COLLISION,
    }
)
"""Message ids accepted unsigned when signing is on (PX4's allow-list,
``src/modules/mavlink/mavlink_sign_control.cpp``)."""


class SigningKeyError(ValueError):
    """A signing key that cannot be used (names what was wrong)."""


def signing_key_bytes(key: str) -> bytes:
    """The 32-byte MAVLink 2 signing secret: 64 hex digits as is, else SHA-256 of the text
    (MAVProxy's ``signing key <passphrase>`` convention).

    Raises:
        SigningKeyError: the key is empty.
    """
    text = key.strip()
    if not text:
        raise SigningKeyError("signing key is empty")
    if len(text) == 64 and all(c in string.hexdigits for c in text):
        return bytes.fromhex(text)
    return hashlib.sha256(text.encode()).digest()


def signing_timestamp_now() -> int:
    """MAVLink signing time: 10 us units since 2015-01-01 UTC (wall clock, as the spec asks)."""
    return int((time.time() - SIGNING_EPOCH_UNIX_S) * 100_000)


def sign_outgoing(mav: Any, key: bytes, link_id: int) -> None:
    """Sign everything the pymavlink encoder ``mav`` sends from now on with the 32-byte ``key``
    on ``link_id``, its signing clock starting at :func:`signing_timestamp_now`.

    Raises:
        SigningKeyError: ``key`` is not 32 bytes.
    """
    if len(key) != 32:
        raise SigningKeyError(f"signing key must be 32 bytes, got {len(key)}")
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.link_id = link_id
    mav.signing.timestamp = signing_timestamp_now()
