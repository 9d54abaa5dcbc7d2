"""MAVLink 2 message signing as both ends of a visland link apply it.

One parser for the secret (``visland sitl --signing-key`` and the companion's ``signing_key``
take the same text) and PX4's list of messages accepted unsigned on a signed link.
"""

from __future__ import annotations

import hashlib
import string

from pymavlink.dialects.v20 import common as mavlink

__all__ = ["UNSIGNED_ALLOWED", "SigningKeyError", "signing_key_bytes"]

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
