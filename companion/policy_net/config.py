"""The learned policy's configuration: :class:`NetConfig` and :class:`CheckpointError`.

:class:`NetConfig` is everything needed to rebuild the networks and the estimator; it is stored
in every checkpoint. No torch here: the estimator reads it too.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from typing import Any

from companion.contract import CAMERA_FOV_DEG, IMAGE_SIZE_PX

__all__ = ["ESTIMATOR_FIELDS", "CheckpointError", "NetConfig"]

ESTIMATOR_FIELDS = (
    "accel_noise_m_s2",
    "bearing_noise_rad",
    "bearing_noise_floor_m",
    "alt_noise_m",
    "alt_noise_fraction",
    "visibility_threshold",
    "acquire_threshold",
    "unsure_threshold",
    "unsure_sigma_scale",
    "unsure_max_tilt_deg",
    "gate_sigma",
    "gate_reset_steps",
    "min_fix_altitude_m",
    "accel_bias_states",
    "accel_bias_sigma_m_s2",
    "accel_bias_walk_m_s2",
    "radar_gate_sigma",
    "radar_full_reset",
    "radar_terrain_slope_deg",
    "bias_learn_min_altitude_m",
    "latency_compensation",
    "land_floor_m",
    "confirm_fixes",
    "confirm_threshold",
    "search_altitude_m",
    "pad_timeout_s",
    "confirm_reset_on_reacquire",
    "envelope_sink_m_s",
    "envelope_tilt_deg",
)
"""The :class:`NetConfig` fields that shape only the pad estimator, the fix and the landing
guard, not a network's weights: a trained network flies with any values of them."""


class CheckpointError(ValueError):
    """A checkpoint file is missing, corrupt, of another format, or does not fit its network."""


def _check_setting_key(key: str) -> None:
    if key not in ESTIMATOR_FIELDS:
        raise CheckpointError(
            f"estimator setting {key!r}: not one that a trained network flies with any value "
            f"of; expected one of {', '.join(ESTIMATOR_FIELDS)}"
        )


@dataclass(frozen=True)
class NetConfig:
    """Everything needed to rebuild the networks and the estimator (stored in checkpoints)."""

    kind: str = "vision"
    """``vision`` (CNN + estimator + LSTM) or ``privileged`` (ground-truth position/velocity)."""
    cnn_channels: tuple[int, ...] = (8, 16, 24, 32)
    cnn_context_layers: int = 0
    """Extra dilated (4) 3x3 convolutions before the heat map: a receptive field that spans the
    image, so a pad larger than the old field (low altitude) is still localised by its cross."""
    lstm_hidden: int = 64
    mlp_hidden: int = 64
    hover_thrust_norm: float = 0.3923
    max_rate_rad_s: tuple[float, float, float] = (3.5, 3.5, 1.5)
    gravity_m_s2: float = 9.80665
    control_dt_s: float = 0.1
    fov_deg: float = CAMERA_FOV_DEG
    image_size_px: int = IMAGE_SIZE_PX
    # PadEstimator noise model (1-sigma)
    accel_noise_m_s2: float = 0.3
    bearing_noise_rad: float = 0.01
    bearing_noise_floor_m: float = 0.03
    alt_noise_m: float = 0.05
    visibility_threshold: float = 0.5
    """The CNN's pad probability at or above which its bearing is a horizontal fix."""
    acquire_threshold: float | None = None
    """The pad probability at or above which a fix may *start* the horizontal estimate (while
    it has none yet); None: ``visibility_threshold``. A lower one lets
    an unfamiliar ground, where the CNN is unsure of a pad it has right, start the estimate,
    while a high ``visibility_threshold`` keeps a confident-looking wrong answer out of an
    estimate that has one (the innovation gate then refuses a wrong start)."""
    unsure_threshold: float | None = None
    """A bearing whose pad probability is at or above this but below ``visibility_threshold``
    is an *unsure* fix: it updates an estimate that already has a horizontal position only if
    it passes the innovation gate (``gate_sigma``, with its noise times
    ``unsure_sigma_scale``), and a refused one never counts towards a re-acquisition. On
    ground the CNN has not seen it is often right but unsure of a pad it sees, and without
    these fixes the estimate flies a whole descent on the IMU; the gate keeps the unsure
    answers of a view without the pad out. None: a bearing below ``visibility_threshold`` is
    not used (an estimate without a position still starts at ``acquire_threshold``)."""
    unsure_sigma_scale: float = 2.0
    """Factor on an unsure fix's horizontal 1-sigma (``unsure_threshold``)."""
    unsure_max_tilt_deg: float | None = None
    """An unsure fix is not used from a view tilted (roll and pitch together) beyond this: the
    ground below is then near the image's edge (half the field of view is 22.5°), where the
    CNN's unsure answers come from views without the pad (severe wind holds 15-20° for
    seconds). None: any tilt."""
    gate_sigma: float = 4.0
    """Innovation gate of the horizontal fix (Mahalanobis distance, 2 dof); 0 disables it."""
    gate_reset_steps: int = 10
    """After this many consecutive gated fixes the estimator re-acquires from the fix."""
    min_fix_altitude_m: float = 1.5
    """Below this the view is a piece of one cross arm and the bearing is a guess: the
    horizontal estimate flies on the IMU prediction (the radar altitude is still used)."""
    # Robustness (issue 16). The defaults are the paper-world model's behaviour, so a checkpoint
    # saved before these keys existed loads and flies exactly as it did.
    hover_input: bool = False
    """The controller reads the autopilot's hover thrust (``Observation.hover_thrust_norm``) as
    an input and centres its thrust output on it: one model for heavier and lighter airframes
    and for Mars. False: ``hover_thrust_norm`` above is baked in."""
    accel_bias_states: bool = False
    """The estimator carries an acceleration-bias state per axis (position, velocity, bias):
    an IMU turn-on bias, and on another planet the difference between its gravity and
    ``gravity_m_s2``, are estimated from the radar and camera fixes instead of integrated."""
    accel_bias_sigma_m_s2: tuple[float, float, float] = (0.3, 0.3, 7.0)
    """Initial 1-sigma of the bias states (north, east, down): down spans Earth to Mars."""
    accel_bias_walk_m_s2: float = 0.02
    """Random walk of the bias states (m/s^2 per sqrt(s))."""
    alt_noise_fraction: float = 0.0
    """Radar noise that grows with range: the altitude fix's 1-sigma is ``alt_noise_m +
    alt_noise_fraction * altitude`` (Table 1's radar: 2 cm + 0.2 % of range)."""
    radar_gate_sigma: float = 0.0
    """Innovation gate of the altitude fix (Mahalanobis, 1 dof; 0: none, every radar reading is
    taken). A spurious radar return (a bird, dust, a multipath echo) 50 m off at 2 m altitude
    otherwise moves the altitude estimate by 50 m, and the controller dives at the ground. After
    ``gate_reset_steps`` refusals in a row the estimate re-acquires from the radar."""
    radar_full_reset: bool = False
    """What a re-acquisition from the radar (``radar_gate_sigma``) restarts. False: the altitude
    alone, the velocity and acceleration-bias estimates kept (a checkpoint saved before this key
    flies as it did). True: the whole vertical axis, as at its first fix — altitude from the
    radar, velocity 0 +- 2 m/s, bias from its prior. The gate refuses the radar for so long
    because the prediction drifted, and a drift is a wrong velocity or bias: over sloped ground
    a tilted range read as an altitude moves the bias tens of m/s^2 in one accepted fix, and
    kept, it drives the altitude away from every later reading."""
    radar_terrain_slope_deg: float = 0.0
    """The steepest ground the radar may look at (0: flat, the radar's range is the height
    above the pad). The radar measures the ground where its beam (body +z) meets it: below the
    vehicle when level, ``altitude x tan(tilt)`` away along the tilt when not, and on a slope,
    among rocks or in a crater field that ground lies up to ``tan(slope) x`` its horizontal
    distance from the pad above or below the pad. The altitude fix's 1-sigma grows by that (in
    quadrature; the vehicle's offset is the estimate's, once it has one), so a reading of
    ground far from the pad — the vehicle's, or the beam's at 30 degrees of tilt from 90 m,
    52 m away — is a weak fix of the altitude above the pad that cannot yank the velocity and
    bias, and a level one over the pad a precise one."""
    bias_learn_min_altitude_m: float = 0.0
    """Below this altitude (m, the fix's: the radar's) the horizontal acceleration-bias states
    (``accel_bias_states``) are held: a camera fix still moves the position and velocity, with
    the bias's uncertainty accounted (a Schmidt "consider" update), but no longer the bias.
    Close to the pad the CNN's errors are not white noise but the same for seconds — the pad
    filling the view, a rover's cab or a ship's deckhouse beside it — and a fix trusted to a few
    centimetres there moves the bias by a tenth of a m/s^2 in half a second; below
    ``min_fix_altitude_m`` nothing corrects it, and the vehicle drifts off the pad while it
    settles. 0: learnt at every altitude (a checkpoint saved before this key flies as it did)."""
    latency_compensation: bool = False
    """The camera fix is computed with the attitude at the image's exposure time
    (``image_time_s``, interpolated between the last two ATTITUDE samples) and carried forward
    to now with the estimated velocity; a repeated image (a lost frame) gives no new fix."""

    # Never land blind (companion.policy_net.guard). On by default: a checkpoint saved before
    # these keys existed flies as it did whenever it confirms the pad above the floor.
    land_floor_m: float | None = 12.0
    """Below this altitude (m, the estimator's) a vision policy descends only with a confirmed
    pad; without one the guard holds and climbs, and gives up after ``pad_timeout_s``. None:
    no guard."""
    confirm_fixes: int = 10
    """Horizontal fixes the estimator took (sure, or unsure through the gate) that confirm the
    pad."""
    confirm_threshold: float | None = 0.75
    """The pad probability a taken fix needs to count towards ``confirm_fixes``; None: any
    fix the estimator took (sure, or unsure through the gate). Chosen on the validation seed
    (docs/DESIGN.md, decisions): unsure fixes of ground without a pad pass the gate often
    enough to confirm a pad that is not there."""
    search_altitude_m: float = 30.0
    """Where the guard climbs to, to widen the view, and holds."""
    pad_timeout_s: float = 30.0
    """Time in the guard without a confirmed pad after which the flight ends: pad not found."""
    confirm_reset_on_reacquire: bool = False
    """A re-acquisition (the estimate restarted from a fix the innovation gate had refused
    ``gate_reset_steps`` times in a row) starts the pad's confirmation again: the fixes that
    confirmed the old estimate were of another place (a parking bay taken for the pad). Off by
    default: on a moving pad a re-acquisition is also how the estimate catches up, and a
    landing-target hand-off to a rover then holds where it should descend (docs/DESIGN.md,
    decisions: never land blind)."""
    envelope_sink_m_s: float | None = None
    """The guard recovers the vehicle — levels it and arrests the descent — whenever the
    estimator's descent speed is above this (m/s), then holds until the pad is confirmed again
    (:mod:`companion.policy_net.guard`). None (the default): off — the recovery and the hold
    trust the estimator's vertical velocity, and where that diverged (a radar reading a slope)
    they climb away instead (docs/DESIGN.md, decisions)."""
    envelope_tilt_deg: float | None = None
    """Likewise for a tilt from level above this (degrees): a policy out of its training's
    states can roll the vehicle over. None (the default): off."""

    def __post_init__(self) -> None:
        if self.kind not in ("vision", "privileged"):
            raise CheckpointError(
                f"net config kind: expected 'vision' or 'privileged', got {self.kind!r}"
            )
        if not 0.0 < self.hover_thrust_norm < 1.0:
            raise CheckpointError(
                f"net config hover_thrust_norm: expected in (0, 1), got {self.hover_thrust_norm}"
            )
        if not (math.isfinite(self.radar_gate_sigma) and self.radar_gate_sigma >= 0):
            raise CheckpointError(
                f"net config radar_gate_sigma: expected >= 0 (0: off), got {self.radar_gate_sigma}"
            )
        if not 0.0 <= self.radar_terrain_slope_deg < 90.0:
            raise CheckpointError(
                "net config radar_terrain_slope_deg: expected in [0, 90) degrees, got "
                f"{self.radar_terrain_slope_deg}"
            )
        lift = self.bias_learn_min_altitude_m
        if not (math.isfinite(lift) and 0.0 <= lift <= 200.0):
            raise CheckpointError(
                f"net config bias_learn_min_altitude_m: expected in [0, 200] m, got {lift}"
            )
        for key in (
            "visibility_threshold",
            "acquire_threshold",
            "unsure_threshold",
            "confirm_threshold",
        ):
            value = getattr(self, key)
            if value is not None and not 0.0 <= value <= 1.0:
                raise CheckpointError(f"net config {key}: expected in [0, 1], got {value}")
        if self.unsure_threshold is not None and not self.gate_sigma > 0:
            raise CheckpointError(
                "net config unsure_threshold: needs the innovation gate (gate_sigma > 0), got "
                f"gate_sigma {self.gate_sigma}"
            )
        tilt = self.unsure_max_tilt_deg
        if tilt is not None and not 0.0 < tilt <= 90.0:
            raise CheckpointError(
                f"net config unsure_max_tilt_deg: expected in (0, 90] or None, got {tilt}"
            )
        if not (math.isfinite(self.unsure_sigma_scale) and self.unsure_sigma_scale >= 1.0):
            raise CheckpointError(
                f"net config unsure_sigma_scale: expected >= 1, got {self.unsure_sigma_scale}"
            )
        floor = self.land_floor_m
        if floor is not None and not (math.isfinite(floor) and 0.0 < floor <= 200.0):
            raise CheckpointError(
                f"net config land_floor_m: expected in (0, 200] m or None, got {floor}"
            )
        if floor is not None and not self.search_altitude_m >= floor:
            raise CheckpointError(
                f"net config search_altitude_m: expected >= land_floor_m ({floor}), got "
                f"{self.search_altitude_m}"
            )
        if not (isinstance(self.confirm_fixes, int) and self.confirm_fixes >= 1):
            raise CheckpointError(
                f"net config confirm_fixes: expected an integer >= 1, got {self.confirm_fixes!r}"
            )
        sink, tilt_limit = self.envelope_sink_m_s, self.envelope_tilt_deg
        if sink is not None and not (math.isfinite(sink) and 2.0 < sink <= 100.0):
            raise CheckpointError(
                f"net config envelope_sink_m_s: expected in (2, 100] m/s or None, got {sink}"
            )
        if tilt_limit is not None and not (
            math.isfinite(tilt_limit) and 30.0 < tilt_limit <= 180.0
        ):
            raise CheckpointError(
                "net config envelope_tilt_deg: expected in (30, 180] degrees or None, got "
                f"{tilt_limit}"
            )
        if not (math.isfinite(self.pad_timeout_s) and self.pad_timeout_s > 0.0):
            raise CheckpointError(
                f"net config pad_timeout_s: expected > 0 s, got {self.pad_timeout_s}"
            )
        if len(self.accel_bias_sigma_m_s2) != 3 or min(self.accel_bias_sigma_m_s2) <= 0:
            raise CheckpointError(
                "net config accel_bias_sigma_m_s2: expected 3 positive values, got "
                f"{self.accel_bias_sigma_m_s2}"
            )
        if len(self.max_rate_rad_s) != 3 or min(self.max_rate_rad_s) <= 0:
            raise CheckpointError(
                f"net config max_rate_rad_s: expected 3 positive values, got {self.max_rate_rad_s}"
            )

    def hover_feature(self, hover_thrust_norm: float) -> float | None:
        """The hover thrust a ``hover_input`` controller is given: the autopilot's, or this
        config's when it reported none (NaN); None for a controller without the input."""
        if not self.hover_input:
            return None
        if math.isfinite(hover_thrust_norm) and 0.0 < hover_thrust_norm < 1.0:
            return float(hover_thrust_norm)
        return self.hover_thrust_norm

    def with_settings(self, settings: Mapping[str, Any]) -> NetConfig:
        """This config with :data:`ESTIMATOR_FIELDS` values replaced (``visland eval
        --estimator``): a trained network flies with any of them. A key outside them or a bad
        value is a :class:`CheckpointError` naming it."""
        for key in settings:
            _check_setting_key(key)
        return replace(self, **dict(settings))

    @staticmethod
    def parse_setting(text: str) -> tuple[str, Any]:
        """``KEY=VALUE`` of an :data:`ESTIMATOR_FIELDS` key, the value read as the field's
        type: ``none`` for an optional one, ``true``/``false``, an integer, a number, or three
        comma-separated numbers. A CheckpointError names what is wrong."""
        key, sep, raw = text.partition("=")
        key, raw = key.strip(), raw.strip()
        if not sep or not key or not raw:
            raise CheckpointError(f"estimator setting {text!r}: expected KEY=VALUE")
        _check_setting_key(key)
        hint = str(NetConfig.__dataclass_fields__[key].type)  # e.g. "float | None"
        kind = hint.removesuffix(" | None")
        try:
            if raw.lower() == "none":
                if kind == hint:
                    raise ValueError("this setting cannot be none")
                value: Any = None
            elif kind == "bool":
                if raw.lower() not in ("true", "false"):
                    raise ValueError("expected true or false")
                value = raw.lower() == "true"
            elif kind.startswith("tuple"):
                value = tuple(float(v) for v in raw.split(","))
            elif kind == "int":
                value = int(raw)
            else:
                value = float(raw)
        except ValueError as exc:
            raise CheckpointError(f"estimator setting {key}={raw}: {exc}") from None
        return key, value

    @staticmethod
    def parse_settings(text: str) -> dict[str, Any]:
        """Several settings in one string, ``KEY=VALUE,KEY=VALUE`` (a repeated ``--estimator``
        flag joined by commas; a vector's own commas stay with its key), each read by
        :meth:`parse_setting`. Empty text: none."""
        parts = re.split(r",(?=\s*[A-Za-z_]\w*\s*=)", text.strip()) if text.strip() else []
        return dict(NetConfig.parse_setting(part) for part in parts)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["cnn_channels"] = list(self.cnn_channels)
        d["max_rate_rad_s"] = list(self.max_rate_rad_s)
        d["accel_bias_sigma_m_s2"] = list(self.accel_bias_sigma_m_s2)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> NetConfig:
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known
        if unknown:
            raise CheckpointError(f"net config: unknown keys {sorted(unknown)}")
        d = dict(d)
        if "cnn_channels" in d:
            d["cnn_channels"] = tuple(int(c) for c in d["cnn_channels"])
        for key in ("max_rate_rad_s", "accel_bias_sigma_m_s2"):
            if key in d:
                d[key] = tuple(float(v) for v in d[key])
        return cls(**d)
