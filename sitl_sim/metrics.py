"""Landing metrics, defined once for the env, the SITL, the expert and every evaluation.

DESIGN.md: landing error is the horizontal distance of the vehicle centre from the pad centre at
touchdown (first ground contact); success means error <= 1 m, vertical speed <= 1 m/s and tilt
<= 20 deg at touchdown.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from companion.contract.record_base import ABSENT, RECORD
from companion.contract.records import EpisodeResultRecord
from sitl_sim.physics.dynamics import ContactEvent

__all__ = [
    "OFF_PAD_M",
    "SUCCESS_MAX_ERROR_M",
    "SUCCESS_MAX_TILT_DEG",
    "SUCCESS_MAX_VERTICAL_SPEED_M_S",
    "EpisodeResult",
    "summarize",
]

SUCCESS_MAX_ERROR_M = 1.0
SUCCESS_MAX_VERTICAL_SPEED_M_S = 1.0
SUCCESS_MAX_TILT_DEG = 20.0
OFF_PAD_M = 2.0
"""A touchdown further than this from the pad centre is an *off-pad touchdown*: an unsafe
failure (the vehicle came down on whatever lay there), counted apart from aborts."""

_RESULT_KEYS = EpisodeResultRecord.required_field_names()
"""The result's own keys: those every ``/episode/result`` message has (the SITL's are extras)."""
_SITE_KEYS = ("touched_pad", "tipped_over")
"""The result's keys on a site (absent on the nominal one)."""


@dataclass(**RECORD)
class EpisodeResult(EpisodeResultRecord):
    """How one episode ended: the ``/episode/result`` message's own fields (its record,
    :class:`~companion.contract.records.EpisodeResultRecord`, declares them once; the SITL's
    extras stay absent), scored here.

    Attributes:
        landed: the vehicle touched the ground (False: timeout).
        time_s: sim time at touchdown (or at the timeout).
        landing_error_m: horizontal distance from the pad centre at touchdown (at the timeout:
            the horizontal distance then; ``success`` is False either way).
        touchdown_speed_m_s: norm of the velocity at touchdown.
        touchdown_vertical_speed_m_s: downward speed at touchdown.
        tilt_deg: angle between body down and world down at touchdown.
        success: the DESIGN.md success criterion.
    """

    @classmethod
    def read(cls, values: Mapping[str, Any]) -> EpisodeResult:
        """The result in a logged ``/episode/result`` message, or in a report's row (their
        other keys left out; a metric logged as null, NaN when written, is NaN again)."""
        site = {k: bool(values[k]) for k in _SITE_KEYS if values.get(k) is not None}
        if values.get("failsafe") is not None:
            site["failsafe"] = str(values["failsafe"])
        if values.get("took_over") is not None:
            site["took_over"] = bool(values["took_over"])
        return cls(
            **{k: math.nan if values[k] is None else values[k] for k in _RESULT_KEYS}, **site
        )

    @classmethod
    def from_contact(cls, contact: ContactEvent) -> EpisodeResult:
        """Scored in the pad's frame: on the nominal site that is NED at the origin; on a site
        (``contact.pad``) the error lies in the pad's plane, the speeds are relative to the
        pad's surface, the tilt is from its normal, and a tip-over fails."""
        pad = contact.pad
        if pad is None:
            pos, vel, tilt_rad = contact.pos_ned_m, contact.vel_ned_m_s, contact.tilt_rad
        else:
            pos, vel, tilt_rad = pad.pos_m, pad.vel_m_s, pad.tilt_rad
        err = float(math.hypot(pos[0], pos[1]))
        speed = float(np.linalg.norm(vel))
        vz = float(vel[2])
        tilt = math.degrees(float(tilt_rad))
        success = (
            err <= SUCCESS_MAX_ERROR_M
            and vz <= SUCCESS_MAX_VERTICAL_SPEED_M_S
            and tilt <= SUCCESS_MAX_TILT_DEG
        )
        site = {}
        if pad is not None:
            success = success and not pad.tipped_over
            site = {"touched_pad": bool(pad.touched_pad), "tipped_over": bool(pad.tipped_over)}
        return cls(
            landed=True,
            time_s=float(contact.time_s),
            landing_error_m=err,
            touchdown_speed_m_s=speed,
            touchdown_vertical_speed_m_s=vz,
            tilt_deg=tilt,
            success=success,
            **site,
        )

    @property
    def off_pad(self) -> bool:
        """Touched down more than :data:`OFF_PAD_M` from the pad: an unsafe failure."""
        return bool(self.landed) and not self.landing_error_m <= OFF_PAD_M

    @classmethod
    def aborted_by(cls, reason: str, time_s: float, pos_ned_m) -> EpisodeResult:
        """The pilot ended the flight in the air (``reason``, e.g. ``pad_not_found``):
        ``pos_ned_m`` relative to the pad then; a failure, with no touchdown."""
        return replace(cls.timeout(time_s, pos_ned_m, None), failsafe=str(reason))

    @classmethod
    def timeout(cls, time_s: float, pos_ned_m, vel_ned_m_s) -> EpisodeResult:
        """A flight that never came down: ``pos_ned_m`` relative to the pad
        (``GroundTruth.pad_relative``)."""
        return cls(
            landed=False,
            time_s=float(time_s),
            landing_error_m=float(math.hypot(pos_ned_m[0], pos_ned_m[1])),
            touchdown_speed_m_s=math.nan,
            touchdown_vertical_speed_m_s=math.nan,
            tilt_deg=math.nan,
            success=False,
        )


def _stats(values: list[float]) -> dict[str, float]:
    arr = np.asarray([v for v in values if math.isfinite(v)], dtype=float)
    if arr.size == 0:
        return {"min": math.nan, "max": math.nan, "mean": math.nan, "std": math.nan}
    return {
        "min": float(arr.min()),
        "max": float(arr.max()),
        "mean": float(arr.mean()),
        "std": float(arr.std()),
    }


def summarize(results: list[EpisodeResult]) -> dict[str, Any]:
    """min/max/mean/std of landing error, touchdown speed, tilt, time; success rate.

    Timeouts count as failures; a flight that never touched down has no landing error (its
    distance at the timeout is in its own row) nor touchdown speed, so the landing-error and
    speed stats cover the ``landed`` episodes only, and ``timeouts`` says how many were left
    out so nothing is hidden (all timed out: the stats are NaN, null in JSON). ``aborts``
    are the flights the pilot ended in the air (``failsafe``: pad not found), counted apart
    from the timeouts; ``off_pad`` the touchdowns more than :data:`OFF_PAD_M` from the pad,
    the unsafe failures. ``not_started`` are the SITL episodes nobody took over from HOLD (a
    companion that never engaged), failures counted apart from the ``timeouts`` of flights
    that ran out of time.
    """
    n = len(results)
    landed = [r for r in results if r.landed]
    return {
        "episodes": n,
        "landed": len(landed),
        "landing_error_m": _stats([r.landing_error_m for r in landed]),
        "touchdown_speed_m_s": _stats([r.touchdown_speed_m_s for r in results]),
        "touchdown_vertical_speed_m_s": _stats([r.touchdown_vertical_speed_m_s for r in results]),
        "tilt_deg": _stats([r.tilt_deg for r in results]),
        "time_s": _stats([r.time_s for r in results]),
        "success_rate": (sum(r.success for r in results) / n) if n else math.nan,
        "timeouts": sum(
            not r.landed and r.failsafe is ABSENT and r.took_over is not False for r in results
        ),
        "not_started": sum(r.took_over is False for r in results),
        "aborts": sum(r.failsafe is not ABSENT for r in results),
        "off_pad": sum(r.off_pad for r in results),
    }
