"""Sensor faults from a scenario's ``[sensors]``: camera latency and frame drops, radar dropouts
and spurious returns, IMU turn-on biases, drawn per episode.

Every key is optional; an absent key is no fault, so a scenario without ``[sensors]`` (or with
an empty one) flies exactly the sensors of ``configs/sim.toml``.

* ``camera_latency_ms = [lo, hi]``: the pipeline delay of the camera, drawn once per episode
  (uniform). The image a policy gets at control time ``t`` shows the scene at ``t - latency``
  and carries that *exposure* time (``Observation.image_time_s``; the camera packet's
  ``time_us`` over MAVLink, where the frame is still sent at ``t``), as a real camera's
  timestamp does. The simulator rounds the latency to whole physics steps (4 ms at 250 Hz) so
  that the rendered pose is exactly the state at the stamped time.
* ``frame_drop_prob``: each frame is lost with this probability (independently). Over MAVLink a
  lost frame is not sent (its frame id is skipped, as a camera's sequence number would be); in
  process the Observation keeps the last delivered image with its old ``image_time_s`` (see
  :meth:`sitl_sim.simulator.Simulator.capture_frame`). The first frame of a flight is always
  delivered: a policy starts from a picture.
* ``radar_dropout_prob``: a reading is invalid with this probability (NaN in process,
  DISTANCE_SENSOR ``UINT16_MAX`` with ``signal_quality = 1`` over MAVLink: what the radar
  sends when it has no return).
* ``radar_outlier_prob`` + ``radar_outlier_m = [lo, hi]``: a spurious return (clutter,
  multipath): the reading is replaced by a range drawn uniformly from ``[lo, hi]`` (clipped to
  the radar's maximum range, which it never reports beyond). A dropout wins over an outlier.
* ``accel_bias_m_s2 = [lo, hi]``, ``gyro_bias_rad_s = [lo, hi]``: per-axis turn-on biases of
  the IMU, constant over the episode: magnitude uniform in ``[lo, hi]`` (``0 <= lo``) with a
  random sign per axis (a datasheet's "turn-on bias +-X"); the bias random walk of
  ``configs/sim.toml`` starts from it. Only HIGHRES_IMU / ``Observation.accel_frd_m_s2`` carry
  them: ATTITUDE is the autopilot estimator's output, whose filter estimates the gyro bias
  away, and the rate loop flies on the true rates, as before.

Randomness, as :mod:`sitl_sim.physics.wind`: one generator per episode keyed by ``(seed, episode
index,
SENSORS_STREAM)``, an entropy no other stream uses, so ``[sensors]`` changes neither the initial
states, the wind nor the sensors' noise streams. It draws the episode's latency and biases first
(always in that order, so a fault added to a scenario does not change the others' values), then
spawns one generator for camera events and one for radar events: the events of one sensor never
shift the other's, nor does the number of IMU or attitude readings (which differs between the
in-process env and the MAVLink SITL's 50 Hz streams).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from companion.table import Section, probability, section_keys, span
from sitl_sim.errors import ConfigError

__all__ = [
    "MAX_CAMERA_LATENCY_MS",
    "SENSORS_STREAM",
    "SENSOR_KEYS",
    "SensorFaults",
    "SensorFaultsConfig",
    "sensor_faults_config_from_table",
]

SENSORS_STREAM = 0x53454E53
"""Third entropy word of the sensor faults' generator (ASCII "SENS"); distinct from
:data:`sitl_sim.physics.wind.WIND_STREAM` and from every two-word key the sampler and sensors
use."""

MAX_CAMERA_LATENCY_MS = 1000.0
"""Upper bound of ``camera_latency_ms``: a frame older than the companion's ``max_age_ms``
(300 ms) already fails it safe; a second is far beyond any camera pipeline worth simulating."""


def _magnitude(unit: str, doc: str, hi: float | None = None) -> Any:
    return span(None, unit=unit, lo=0.0, hi=hi, doc=doc)


@dataclass(frozen=True)
class SensorFaultsConfig(Section):
    """The ``[sensors]`` section (None / 0: that fault is off).

    Attributes:
        camera_latency_ms: range of the per-episode camera latency, ms (``0 <= lo <= hi <=``
            :data:`MAX_CAMERA_LATENCY_MS`).
        frame_drop_prob: probability that a camera frame is lost, in [0, 1].
        radar_dropout_prob: probability that a radar reading is invalid, in [0, 1].
        radar_outlier_prob: probability of a spurious radar return, in [0, 1].
        radar_outlier_m: range of the spurious returns, m (``0 <= lo <= hi``); required when
            ``radar_outlier_prob > 0``.
        accel_bias_m_s2: magnitude range of the accelerometer turn-on bias per axis, m/s^2.
        gyro_bias_rad_s: magnitude range of the gyro turn-on bias per axis, rad/s.
        source: where it came from (for error messages).
    """

    SECTION: ClassVar[str] = "sensors"

    camera_latency_ms: tuple[float, float] | None = _magnitude(
        "ms", "camera pipeline delay, drawn per episode (absent: none)", MAX_CAMERA_LATENCY_MS
    )
    frame_drop_prob: float = probability("each camera frame is lost (the first never)")
    radar_dropout_prob: float = probability("a radar reading is invalid (no return)")
    radar_outlier_prob: float = probability(
        "a spurious radar return (clutter, multipath); needs radar_outlier_m"
    )
    radar_outlier_m: tuple[float, float] | None = _magnitude(
        "m", "range of the spurious returns (with radar_outlier_prob > 0 only)"
    )
    accel_bias_m_s2: tuple[float, float] | None = _magnitude(
        "m/s^2", "accelerometer turn-on bias magnitude per axis, random sign (absent: none)"
    )
    gyro_bias_rad_s: tuple[float, float] | None = _magnitude(
        "rad/s", "gyro turn-on bias magnitude per axis, random sign (absent: none)"
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        where = f"{self.source}: [sensors]"
        if self.radar_outlier_prob > 0.0 and self.radar_outlier_m is None:
            raise ConfigError(
                f"{where} radar_outlier_prob = {self.radar_outlier_prob} needs radar_outlier_m "
                "= [lo, hi] (the range of the spurious returns, m)"
            )
        if self.radar_outlier_m is not None and self.radar_outlier_prob == 0.0:
            raise ConfigError(
                f"{where} radar_outlier_m is set but radar_outlier_prob is 0; expected both "
                "(or neither)"
            )


SENSOR_KEYS = section_keys(SensorFaultsConfig)


def sensor_faults_config_from_table(table: Any, where: str) -> SensorFaultsConfig:
    """Check and type a scenario file's ``[sensors]`` table (``where`` names the file)."""
    return SensorFaultsConfig.from_table(table, where)


class SensorFaults:
    """The sensor faults of one episode: the drawn latency and biases, and the two event
    generators (camera, radar). Stateful: one object serves one flight
    (:meth:`for_episode` again to re-fly it).

    Attributes:
        camera_latency_s: the episode's camera latency, s (0 without ``camera_latency_ms``).
        accel_bias_frd_m_s2: (3,) accelerometer turn-on bias, or None.
        gyro_bias_frd_rad_s: (3,) gyro turn-on bias, or None.
    """

    def __init__(self, config: SensorFaultsConfig, rng: np.random.Generator) -> None:
        self.config = config
        # Every draw is made whether or not its fault is on: turning one fault on never changes
        # another's values.
        latency_u = float(rng.random())
        accel = _signed(rng, config.accel_bias_m_s2)
        gyro = _signed(rng, config.gyro_bias_rad_s)
        lat = config.camera_latency_ms
        self.camera_latency_s = (
            0.0 if lat is None else 1e-3 * (lat[0] + (lat[1] - lat[0]) * latency_u)
        )
        self.accel_bias_frd_m_s2 = accel if config.accel_bias_m_s2 is not None else None
        self.gyro_bias_frd_rad_s = gyro if config.gyro_bias_rad_s is not None else None
        self._camera_rng, self._radar_rng = rng.spawn(2)
        self._frames = 0
        self.frames_dropped = 0
        self.radar_dropouts = 0
        self.radar_outliers = 0

    @classmethod
    def for_episode(cls, config: SensorFaultsConfig, seed: int, episode_index: int) -> SensorFaults:
        """The faults of episode ``episode_index`` of ``seed``: a pure function of the three."""
        return cls(config, np.random.default_rng([int(seed), int(episode_index), SENSORS_STREAM]))

    def frame_dropped(self) -> bool:
        """Whether the next camera frame is lost (call once per frame, in order). The first
        frame is always delivered."""
        self._frames += 1
        if self._frames == 1:
            return False
        dropped = float(self._camera_rng.random()) < self.config.frame_drop_prob
        self.frames_dropped += dropped
        return dropped

    def radar_reading(self, range_m: float, max_range_m: float) -> float:
        """The radar's reading with this reading's fault applied (call once per reading, in
        order): NaN for a dropout, a spurious range for an outlier, else ``range_m``."""
        u_drop, u_out, u_value = self._radar_rng.random(3)  # always three: readings stay aligned
        cfg = self.config
        if u_drop < cfg.radar_dropout_prob:
            self.radar_dropouts += 1
            return math.nan
        if u_out < cfg.radar_outlier_prob and cfg.radar_outlier_m is not None:
            self.radar_outliers += 1
            lo, hi = cfg.radar_outlier_m
            return min(lo + (hi - lo) * float(u_value), max_range_m)
        return range_m


def _signed(rng: np.random.Generator, magnitude: tuple[float, float] | None) -> np.ndarray:
    """Three per-axis values: magnitude uniform in ``magnitude`` (``(0, 0)`` when None), random
    sign. Six draws either way."""
    u = rng.random(3)
    sign = np.where(rng.random(3) < 0.5, -1.0, 1.0)
    lo, hi = magnitude if magnitude is not None else (0.0, 0.0)
    return sign * (lo + (hi - lo) * u)
