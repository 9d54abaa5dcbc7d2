"""Small stand-ins the unit tests share: decoded MAVLink messages without a link, one step of
a logged episode as the observation the companion built in flight, and the CLI run as a user
runs it."""

from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace
from typing import Any

import numpy as np

from companion.contract import Observation
from training.provenance import REPO

__all__ = [
    "NO_RETURN_CM",
    "FakeMsg",
    "attitude_msg",
    "episode_observation",
    "imu_msg",
    "range_msg",
    "visland",
]

NO_RETURN_CM = 65535
"""DISTANCE_SENSOR ``current_distance`` of a rangefinder with no return (UINT16_MAX)."""


def visland(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``visland ARGS`` as its own process from the repository root, output captured."""
    return subprocess.run(
        [sys.executable, "-m", "tools.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
    )


class FakeMsg(SimpleNamespace):
    """A stand-in for a decoded pymavlink message: its fields, ``get_type()`` and
    ``get_srcComponent()`` (the autopilot's component, 1)."""

    def get_type(self) -> str:
        return self.name

    def get_srcComponent(self) -> int:  # pymavlink's name
        return 1


def range_msg(time_boot_ms: int, range_cm: int, quality: int = 100, **fields: Any) -> FakeMsg:
    """DISTANCE_SENSOR of the downward rangefinder (orientation 25, 0-150 m) reading
    ``range_cm`` (:data:`NO_RETURN_CM`: no return) at signal ``quality``; ``fields`` replace
    any other."""
    values = dict(
        time_boot_ms=time_boot_ms,
        min_distance=0,
        max_distance=15000,
        current_distance=range_cm,
        orientation=25,
        signal_quality=quality,
    )
    return FakeMsg(name="DISTANCE_SENSOR", **{**values, **fields})


def attitude_msg(time_boot_ms: int, **fields: Any) -> FakeMsg:
    """ATTITUDE of a level vehicle, not rotating; ``fields`` replace any field."""
    values = dict(roll=0.0, pitch=0.0, yaw=0.0, rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0)
    return FakeMsg(name="ATTITUDE", time_boot_ms=time_boot_ms, **{**values, **fields})


def imu_msg(time_usec: int, **fields: Any) -> FakeMsg:
    """HIGHRES_IMU of a level vehicle at rest (1 g up, no rotation, accel and gyro fields
    updated); ``fields`` replace any field."""
    values = dict(xacc=0.0, yacc=0.0, zacc=-9.81, xgyro=0.0, ygyro=0.0, zgyro=0.0)
    return FakeMsg(
        name="HIGHRES_IMU", time_usec=time_usec, fields_updated=0x3F, **{**values, **fields}
    )


def episode_observation(
    ep: Any, t: int, image_time_s: float, time_s: float, **fields: Any
) -> Observation:
    """Step ``t`` of a loaded episode (:class:`training.dataset.Episode` with images) as the
    companion's :class:`Observation`: the image stamped ``image_time_s``, attitude, range and
    IMU stamped ``time_s``; ``fields`` add the rest (``hover_thrust_norm``...)."""
    return Observation(
        image=np.ascontiguousarray(ep.images[t]),
        image_time_s=image_time_s,
        attitude_rad=ep.attitude_rad[t],
        rate_frd_rad_s=ep.rate_frd_rad_s[t],
        attitude_time_s=time_s,
        range_m=float(ep.range_m[t]),
        range_time_s=time_s,
        accel_frd_m_s2=ep.accel_frd_m_s2[t],
        imu_time_s=time_s,
        frame_id=int(ep.frame_id[t]),
        **fields,
    )
