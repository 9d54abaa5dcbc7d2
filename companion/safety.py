"""The safety monitor: when to stop flying the policy, and the limits on what it may command.

Failsafe reasons (:class:`~companion.states.FailsafeReason`; each ends the policy's control: the
companion requests LAND and stops sending setpoints, so the autopilot flies the landing itself):

* ``camera_stale`` / ``telemetry_stale`` — the newest frame, ATTITUDE, HIGHRES_IMU or
  DISTANCE_SENSOR (and ODOMETRY for a privileged policy) was received more than ``max_age_s``
  ago (default 600 ms, see :data:`DEFAULT_MAX_AGE_S` for why);
* ``range_invalid`` — near the ground (the last valid range below ``near_ground_m``) the radar
  has given no valid range for ``max_age_s``: the policy would descend blind;
* ``policy_error`` — the policy raised or produced a non-finite command.

Clamps (counted, never a failsafe): thrust to ``[thrust_min, thrust_max]``, each body rate to
``±max_rate_rad_s`` (PX4's MC_*RATE_MAX-like limits; the SITL clamps to the same defaults).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from companion.contract import Command
from companion.link import mavlink
from companion.states import Failsafe, FailsafeReason
from companion.telemetry import TelemetryStore

__all__ = [
    "DEFAULT_MAX_AGE_S",
    "SafetyConfig",
    "SafetyError",
    "SafetyMonitor",
    "TouchdownDetector",
]

DEFAULT_MAX_AGE_S = 0.6
"""The staleness limit: long enough for a lossy link, short enough to act before the autopilot.

The slowest inputs (camera frames, DISTANCE_SENSOR) come at 10 Hz. On a link losing 10 % of
datagrams with 50 ms of jitter (the `[link]` the companion is tested through), a gap longer
than the limit needs ``n`` consecutive losses: with 300 ms (the earlier default, three frame
periods) two losses and a later-than-usual datagram do it, p ≈ 0.1² / 2 per frame — a false
failsafe every ~10 s over two 10 Hz streams (measured: the first real-time flight through that
link failed safe after 1.8 s, "newest frame 303 ms old"). With 600 ms it needs five losses, p ≈
0.1⁵ / 2 + 0.1⁶ ≈ 6e-6 per frame, ~0.5 % of 40-s flights. It stays below the autopilot's
offboard-loss timeout (PX4 COM_OF_LOSS_T = 1 s), so on a real outage the companion still
notices first and asks for LAND while the link may still carry the request."""


class SafetyError(ValueError):
    """A safety limit is configured wrongly (names the field and the expected range)."""


@dataclass(frozen=True)
class SafetyConfig:
    """Limits of the safety monitor.

    Attributes:
        max_age_s: oldest acceptable camera frame / telemetry sample (receive time).
        near_ground_m: below this (last valid range) a missing range is a failsafe.
        thrust_min / thrust_max: collective thrust clamp (normalised).
        max_rate_rad_s: (roll, pitch, yaw) rate clamp, rad/s.
    """

    max_age_s: float = DEFAULT_MAX_AGE_S
    near_ground_m: float = 10.0
    thrust_min: float = 0.0
    thrust_max: float = 1.0
    max_rate_rad_s: tuple[float, float, float] = (3.5, 3.5, 1.5)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_age_s) and self.max_age_s > 0):
            raise SafetyError(f"max_age_s = {self.max_age_s}; expected > 0")
        if not 0.0 <= self.thrust_min < self.thrust_max <= 1.0:
            raise SafetyError(
                f"thrust clamp [{self.thrust_min}, {self.thrust_max}]; expected 0 <= min < max <= 1"
            )
        if len(self.max_rate_rad_s) != 3 or not all(
            math.isfinite(r) and r > 0 for r in self.max_rate_rad_s
        ):
            raise SafetyError(f"max_rate_rad_s = {self.max_rate_rad_s}; expected 3 values > 0")
        if not self.near_ground_m >= 0:
            raise SafetyError(f"near_ground_m = {self.near_ground_m}; expected >= 0")


class SafetyMonitor:
    """Checks inputs before each command and clamps each command."""

    def __init__(self, config: SafetyConfig) -> None:
        self.config = config
        self.clamped = 0
        self._limits = np.asarray(config.max_rate_rad_s, dtype=float)

    def check(
        self,
        now_s: float,
        store: TelemetryStore,
        last_frame_rx_s: float | None,
        need_odometry: bool,
    ) -> Failsafe | None:
        """The failsafe, or None when the inputs are fresh and sane."""
        max_age = self.config.max_age_s
        frame_age = math.inf if last_frame_rx_s is None else now_s - last_frame_rx_s
        if frame_age > max_age:
            return Failsafe(
                FailsafeReason.CAMERA_STALE,
                f"newest frame {frame_age * 1e3:.0f} ms old (> {max_age * 1e3:.0f})",
            )
        names = ("attitude", "imu", "range") + (("odometry",) if need_odometry else ())
        age, worst = store.max_age_s(names, now_s)
        if age > max_age:
            return Failsafe(
                FailsafeReason.TELEMETRY_STALE,
                f"{worst} {age * 1e3:.0f} ms old (> {max_age * 1e3:.0f})",
            )
        last_valid = store.last_valid_range
        if (
            last_valid is not None
            and last_valid.range_m < self.config.near_ground_m
            and now_s - last_valid.rx_s > max_age
        ):
            return Failsafe(
                FailsafeReason.RANGE_INVALID,
                f"no valid range for {(now_s - last_valid.rx_s) * 1e3:.0f} ms at "
                f"{last_valid.range_m:.1f} m",
            )
        return None

    def clamp(self, command: Command) -> tuple[Command, bool]:
        """The command within the limits, and whether anything was clipped."""
        cfg = self.config
        thrust = min(cfg.thrust_max, max(cfg.thrust_min, command.thrust_norm))
        rates = np.clip(command.rate_frd_rad_s, -self._limits, self._limits)
        clipped = thrust != command.thrust_norm or bool(np.any(rates != command.rate_frd_rad_s))
        if not clipped:
            return command, False
        self.clamped += 1
        return Command(thrust_norm=thrust, rate_frd_rad_s=rates), True


@dataclass(eq=False)
class TouchdownDetector:
    """Touchdown from the radar and the IMU, or from the autopilot's own land detector.

    On the ground when EXTENDED_SYS_STATE has said ON_GROUND for ``landed_hold_s`` (two
    messages at 5 Hz: the SITL's detector, like PX4's first stage, already says so within 1 cm
    above the ground, and cutting the thrust there drops the vehicle), or when for ``window_s``
    every range reading is at most ``range_m``, their least-squares trend is within
    ``±still_m_s`` and their spread within ``still_m``, with the gyro quiet (``‖ω‖ <=
    gyro_quiet_rad_s``). Measured against the 2 cm radar noise: "range below 0.3 m" cut the
    thrust in the air (a 2.3 m/s drop), and a 0.5 s spread test fired 3 cm above the ground at
    the expert's 0.17 m/s touchdown speed; the 0.8 s trend (slope noise ≈ 0.026 m/s) does not.
    """

    range_m: float = 0.15
    still_m: float = 0.08
    still_m_s: float = 0.05
    window_s: float = 0.8
    gyro_quiet_rad_s: float = 0.1
    landed_hold_s: float = 0.1
    _readings: deque[tuple[float, float]] = field(init=False, default_factory=deque)
    _landed_rx: float = field(init=False, default=-math.inf)
    _on_ground_since: float | None = field(init=False, default=None)

    def update(self, store: TelemetryStore, since_rx_s: float) -> bool:
        """True once on the ground (``since_rx_s``: ignore landed states received earlier)."""
        landed = store.landed
        if landed is not None and landed.rx_s >= since_rx_s and landed.rx_s != self._landed_rx:
            self._landed_rx = landed.rx_s
            if landed.landed_state != mavlink.MAV_LANDED_STATE_ON_GROUND:
                self._on_ground_since = None
            elif self._on_ground_since is None:
                self._on_ground_since = landed.rx_s
        if self._on_ground_since is not None and (
            self._landed_rx - self._on_ground_since >= self.landed_hold_s
        ):
            return True
        rng = store.range
        if rng is None or (self._readings and rng.time_s <= self._readings[-1][0]):
            return False
        if not rng.valid or rng.range_m > self.range_m:
            self._readings.clear()
            return False
        self._readings.append((rng.time_s, rng.range_m))
        while self._readings and rng.time_s - self._readings[0][0] > self.window_s + 1e-6:
            self._readings.popleft()
        if rng.time_s - self._readings[0][0] < self.window_s - 1e-6:
            return False
        t = np.array([k for k, _ in self._readings])
        r = np.array([v for _, v in self._readings])
        slope = float(np.polyfit(t - t[0], r, 1)[0]) if len(r) >= 3 else math.inf
        imu = store.imu
        quiet = imu is not None and float(np.linalg.norm(imu.gyro_frd_rad_s)) <= (
            self.gyro_quiet_rad_s
        )
        return quiet and abs(slope) <= self.still_m_s and float(r.max() - r.min()) <= self.still_m
