"""The messages every part of visland shares with the companion: Command, Observation and the
privileged GroundTruth.

Frames are MAVLink's: NED world, FRD body. Times are simulation (or autopilot boot) seconds.

* ``Command`` is exactly a SET_ATTITUDE_TARGET with ``type_mask = 128`` (attitude ignored):
  collective thrust normalised to ``[0, 1]`` of the vehicle's total maximum thrust, and body
  rates in FRD. Expert labels and learned policies speak this same space.
* ``Observation`` is what a deployable policy may see: the downward camera image, the attitude
  estimate and body rates (ATTITUDE), the radar range (DISTANCE_SENSOR, along the body down axis)
  and the specific force (HIGHRES_IMU). Ground truth never travels in an Observation.
* ``GroundTruth`` is the privileged channel (PX4's ``*_groundtruth`` topics): the simulator's
  true state, or on a SITL link the companion's reading of ODOMETRY. Only *privileged* policies
  (the MPC expert, the paper's LSTM-only rows) read it; hardware has none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "CAMERA_FOV_DEG",
    "IMAGE_SIZE_PX",
    "Command",
    "ContractError",
    "GroundTruth",
    "Observation",
    "quat_from_euler",
    "quat_to_rotation",
    "rotation_zyx",
]

IMAGE_SIZE_PX = 128
"""Side of the square mono8 camera image every policy is trained on (paper Table 1)."""
CAMERA_FOV_DEG = 45.0
"""Full field of view of that image (paper Table 1)."""


def rotation_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) rotation body FRD -> NED from ZYX Euler angles (MAVLink ATTITUDE, an
    Observation's ``attitude_rad``; a pad's yaw, pitch and roll)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def quat_to_rotation(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation body FRD -> world NED of a unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = (float(v) for v in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` of ZYX Euler angles (yaw, then pitch, then roll)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


class ContractError(ValueError):
    """A Command or Observation that breaks the contract (shape, range, finiteness)."""


def _vec3(name: str, value: object) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ContractError(f"{name}: expected shape (3,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ContractError(f"{name}: expected finite values, got {arr.tolist()}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class Command:
    """Collective thrust + body rates: SET_ATTITUDE_TARGET with type_mask 128.

    Attributes:
        thrust_norm: collective thrust as a fraction of the total maximum thrust, in [0, 1].
        rate_frd_rad_s: (3,) body rates p, q, r about FRD axes, rad/s.
    """

    thrust_norm: float
    rate_frd_rad_s: np.ndarray

    def __post_init__(self) -> None:
        thrust = float(self.thrust_norm)
        if not math.isfinite(thrust) or not 0.0 <= thrust <= 1.0:
            raise ContractError(f"thrust_norm: expected a finite value in [0, 1], got {thrust}")
        object.__setattr__(self, "thrust_norm", thrust)
        object.__setattr__(self, "rate_frd_rad_s", _vec3("rate_frd_rad_s", self.rate_frd_rad_s))

    @classmethod
    def from_array(cls, action: np.ndarray) -> Command:
        """Build from a gymnasium action ``[thrust_norm, p, q, r]`` (shape (4,))."""
        arr = np.asarray(action, dtype=np.float64)
        if arr.shape != (4,):
            raise ContractError(
                f"action: expected shape (4,) [thrust_norm, p, q, r], got {arr.shape}"
            )
        return cls(thrust_norm=float(arr[0]), rate_frd_rad_s=arr[1:4])

    def as_array(self) -> np.ndarray:
        """``[thrust_norm, p, q, r]`` as float32, the gymnasium action layout."""
        return np.concatenate(([self.thrust_norm], self.rate_frd_rad_s)).astype(np.float32)


@dataclass(frozen=True)
class Observation:
    """What a deployable (non-privileged) policy sees at one camera frame.

    Attributes:
        image: (128, 128) uint8 mono8 image, row 0 = top = body forward, column 0 = body left.
        image_time_s: exposure time of the image: the sim time of the scene it shows (earlier
            than the other readings' times with camera latency; not advancing when a frame was
            lost and the last one is repeated).
        attitude_rad: (3,) roll, pitch, yaw (rad), from ATTITUDE.
        rate_frd_rad_s: (3,) body rates from ATTITUDE.
        attitude_time_s: time stamp of the attitude sample.
        range_m: radar range along the body down axis (m); NaN when the sensor reports invalid.
        range_time_s: time stamp of the range sample.
        accel_frd_m_s2: (3,) specific force from HIGHRES_IMU (about (0, 0, -g) at hover).
        imu_time_s: time stamp of the IMU sample.
        hover_thrust_norm: the vehicle's hover thrust (thrust_norm that holds altitude), as the
            autopilot reports it (PX4 ``MPC_THR_HOVER``, ArduPilot ``MOT_THST_HOVER``, read at
            connect time); NaN when it has not reported one. It is how one policy knows a
            heavier or lighter airframe, or Mars.
    """

    image: np.ndarray
    image_time_s: float
    attitude_rad: np.ndarray
    rate_frd_rad_s: np.ndarray
    attitude_time_s: float
    range_m: float
    range_time_s: float
    accel_frd_m_s2: np.ndarray
    imu_time_s: float
    frame_id: int = field(default=0)
    hover_thrust_norm: float = math.nan

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.shape != (IMAGE_SIZE_PX, IMAGE_SIZE_PX) or img.dtype != np.uint8:
            raise ContractError(
                f"image: expected ({IMAGE_SIZE_PX}, {IMAGE_SIZE_PX}) uint8, "
                f"got {img.shape} {img.dtype}"
            )
        for name in ("attitude_rad", "rate_frd_rad_s", "accel_frd_m_s2"):
            object.__setattr__(self, name, _vec3(name, getattr(self, name)))
        rng = float(self.range_m)
        if not (math.isnan(rng) or rng >= 0.0):
            raise ContractError(f"range_m: expected >= 0 or NaN (invalid), got {rng}")
        object.__setattr__(self, "range_m", rng)
        hover = float(self.hover_thrust_norm)
        if not (math.isnan(hover) or 0.0 < hover < 1.0):
            raise ContractError(
                f"hover_thrust_norm: expected in (0, 1) or NaN (not reported), got {hover}"
            )
        object.__setattr__(self, "hover_thrust_norm", hover)


PAD_ODOMETRY_COMPONENT = 25
"""MAV_COMP_ID_USER1: on a SITL link with ``--groundtruth`` and a landing site, the pad's state
travels as ODOMETRY from this component of the autopilot's system (pose in LOCAL_NED, velocity
in LOCAL_NED): the privileged channel's pad, as the vehicle's own ODOMETRY is its state."""
PAD_STATE_FIELDS = ("pad_pos_ned_m", "pad_vel_ned_m_s", "pad_quat_wxyz", "pad_accel_ned_m_s2")
"""GroundTruth's pad state: all four or none (the nominal pad, still at the origin)."""
_OPTIONAL_VECTORS = (
    ("accel_ned_m_s2", 3),
    ("rotor_thrust_n", 4),
    ("wind_ned_m_s", 3),
    ("pad_pos_ned_m", 3),
    ("pad_vel_ned_m_s", 3),
    ("pad_quat_wxyz", 4),
    ("pad_accel_ned_m_s2", 3),
)


def _vec(name: str, value: object, n: int) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)  # no copy for a float64 array: the caller's values
    if arr.shape != (n,):
        raise ContractError(f"{name}: expected shape ({n},), got {arr.shape}")
    return arr


@dataclass(frozen=True)
class GroundTruth:
    """Privileged state at one instant (never part of an Observation).

    Attributes:
        time_s: sim (autopilot boot) time of the state.
        pos_ned_m: (3,) position of the vehicle centre, pad centre = origin.
        vel_ned_m_s: (3,) velocity.
        quat_wxyz: (4,) attitude, body FRD -> NED.
        rate_frd_rad_s: (3,) body rates.
        accel_ned_m_s2: (3,) acceleration, or None where the source has none (ODOMETRY).
        rotor_thrust_n: (4,) rotor thrusts, or None where the source has none (ODOMETRY).
        wind_ned_m_s: (3,) wind at the vehicle (NED, m/s) in a simulated world with wind, else
            None (still air, or a source that cannot know it).
        pad_pos_ned_m, pad_vel_ned_m_s, pad_quat_wxyz, pad_accel_ned_m_s2: the pad's surface
            centre now on a site that is not flat and still (a rover, a deck, a slope, rocks):
            position, velocity, attitude (pad frame x forward, y right, z down -> NED) and
            acceleration; all four None for the nominal still pad at the origin, lying level.
    """

    time_s: float
    pos_ned_m: np.ndarray
    vel_ned_m_s: np.ndarray
    quat_wxyz: np.ndarray
    rate_frd_rad_s: np.ndarray
    accel_ned_m_s2: np.ndarray | None = None
    rotor_thrust_n: np.ndarray | None = None
    wind_ned_m_s: np.ndarray | None = None
    pad_pos_ned_m: np.ndarray | None = None
    pad_vel_ned_m_s: np.ndarray | None = None
    pad_quat_wxyz: np.ndarray | None = None
    pad_accel_ned_m_s2: np.ndarray | None = None

    def __post_init__(self) -> None:
        # Shapes only: finiteness is the producer's business (the simulator raises its own
        # SimStateError on a non-finite state; a log reader checks what it reads).
        for name, n in (
            ("pos_ned_m", 3),
            ("vel_ned_m_s", 3),
            ("quat_wxyz", 4),
            ("rate_frd_rad_s", 3),
        ):
            object.__setattr__(self, name, _vec(name, getattr(self, name), n))
        for name, n in _OPTIONAL_VECTORS:
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _vec(name, value, n))
        pad = [getattr(self, name) is None for name in PAD_STATE_FIELDS]
        if any(pad) and not all(pad):
            raise ContractError(f"{', '.join(PAD_STATE_FIELDS)}: expected all four or none")

    @property
    def pad_relative(self) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) of the vehicle relative to the pad's surface centre (NED): the
        state itself for the nominal pad at the origin."""
        if self.pad_pos_ned_m is None or self.pad_vel_ned_m_s is None:
            return self.pos_ned_m, self.vel_ned_m_s
        return self.pos_ned_m - self.pad_pos_ned_m, self.vel_ned_m_s - self.pad_vel_ned_m_s

    def as_dict(self) -> dict[str, np.ndarray]:
        """The gymnasium ``info["groundtruth"]`` layout (``wind_ned_m_s`` only in wind and the
        pad's state only on a site, like the ground-truth log record)."""
        out = {
            "pos_ned_m": self.pos_ned_m.copy(),
            "vel_ned_m_s": self.vel_ned_m_s.copy(),
            "quat_wxyz": self.quat_wxyz.copy(),
            "rate_frd_rad_s": self.rate_frd_rad_s.copy(),
        }
        for name in ("wind_ned_m_s", *PAD_STATE_FIELDS):
            value = getattr(self, name)
            if value is not None:
                out[name] = np.array(value, dtype=float)
        return out
