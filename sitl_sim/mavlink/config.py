"""What ``visland sitl`` takes: :class:`SitlConfig` (every field is a ``--flag``), its checks,
the ``--signing-key`` secret, and the argparse plumbing between the two."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any

from companion.contract.signing import SigningKeyError, signing_key_bytes
from companion.options import add_arguments, option, redacted_dict, values_from_args
from sitl_sim.autopilot.ardupilot import ardupilot_params
from sitl_sim.autopilot.params import parse_param_overrides, with_param
from sitl_sim.autopilot.px4 import AutopilotParams
from sitl_sim.mavlink.endpoint import SitlError

__all__ = [
    "SitlConfig",
    "add_sitl_arguments",
    "initial_params",
    "sitl_config_from_args",
]


def _link(doc: str) -> Any:
    """A ``--link-*`` flag: the scenario's ``[link]`` key of that name, overridden."""
    return option(None, f"impaired link (real time): {doc} (default: the scenario's [link])", float)


@dataclass(frozen=True)
class SitlConfig:
    """Everything ``visland sitl`` takes; each field is a ``--flag`` (underscores -> dashes).

    Saved (key redacted) in every flight log's metadata.
    """

    host: str = option("127.0.0.1", "address to bind the MAVLink port on (loopback by default)")
    mavlink_port: int = option(14580, "local UDP port of the offboard link (PX4 SITL: 14580)")
    remote_host: str = option("127.0.0.1", "where the offboard API listens")
    remote_port: int = option(14540, "UDP port the offboard API listens on (PX4 SITL: 14540)")
    gcs: bool = option(
        True, "ground-station link (QGroundControl, MAVProxy) beside the offboard link"
    )
    gcs_port: int = option(18570, "local UDP port of the ground-station link (PX4 SITL: 18570)")
    gcs_remote_host: str = option("127.0.0.1", "where the ground station listens")
    gcs_remote_port: int = option(14550, "UDP port the ground station listens on (QGC: 14550)")
    camera_host: str = option("127.0.0.1", "where camera frames are sent")
    camera_port: int = option(5600, "UDP port camera frames are sent to")
    lockstep: bool = option(True, "lockstep (sim waits for the companion) vs real time")
    lockstep_timeout_s: float = option(
        0.5, "wall seconds to wait for the answer to one frame before going on without it"
    )
    lockstep_require_stamp: bool = option(
        True, "an answer must be stamped (time_boot_ms) at or after the frame's time"
    )
    speed: float = option(1.0, "sim seconds per wall second when paced (real time, HOLD)")
    episodes: int = option(1, "consecutive episodes to fly, then exit")
    first_episode: int = option(
        0, "index of the first episode (parallel SITLs split one seed's episodes)"
    )
    seed: int = option(
        0,
        "episode i starts at InitialStateSampler(scenario, seed).sample(i) (`visland sitl`: "
        "the evaluation seed, training.seeds.EVAL_SEED, as eval, fly and demo)",
    )
    scenario: str | None = option(None, "scenario TOML (default configs/scenario.toml)", str)
    sim_config: str | None = option(None, "simulation TOML (default configs/sim.toml)", str)
    vehicle_config: str | None = option(None, "vehicle TOML (default configs/vehicle.toml)", str)
    episode_timeout_s: float | None = option(
        None, "flight time after which an episode ends as a timeout (default: sim.toml)", float
    )
    hold_timeout_s: float = option(
        120.0, "sim seconds in HOLD without a take-over before the episode is abandoned"
    )
    groundtruth: bool = option(False, "publish ground truth as ODOMETRY (privileged clients)")
    live: str = option(
        "", "serve a live view of the truth in Foxglove on [HOST:]PORT ('visland[live]'); '' = off"
    )
    signing_key: str | None = option(
        None, "MAVLink 2 signing: 64 hex digits, or a passphrase (key = SHA-256 of it)", str
    )
    log_dir: str | None = option(
        "runs/sitl/flights", "folder for one MCAP flight log per episode (empty: no logs)", str
    )
    render: bool = option(True, "render the pybullet camera (off: black frames, faster)")
    noiseless: bool = option(False, "turn every sensor noise off")
    start_armed: bool = option(True, "episodes start armed (the vehicle is flying)")
    attitude_rate_hz: float = option(50.0, "ATTITUDE and ATTITUDE_QUATERNION rate")
    imu_rate_hz: float = option(50.0, "HIGHRES_IMU rate")
    distance_rate_hz: float = option(10.0, "DISTANCE_SENSOR rate")
    groundtruth_rate_hz: float = option(50.0, "ODOMETRY rate with --groundtruth")
    max_wall_s: float | None = option(None, "stop after this many wall seconds (safety net)", float)
    # Overrides of the scenario's [link] key of the same name (an impaired link, real time only)
    link_loss_prob: float | None = _link("datagram loss probability")
    link_delay_ms: float | None = _link("fixed one-way delay, ms")
    link_jitter_ms: float | None = _link("uniform extra delay [0, J] ms, order kept")
    link_duplicate_prob: float | None = _link("probability a datagram arrives twice")
    link_reorder_prob: float | None = _link("probability a datagram jumps the queue")
    link_cut_at_s: float | None = _link("dead for good from this flight time, s")
    autopilot: str = option(
        "px4",
        "autopilot profile on the wire: px4 (PX4 modes, OFFBOARD) or ardupilot (ArduCopter 4.5: "
        "GUIDED_NOGPS, GUID_OPTIONS, GUID_TIMEOUT, MOT_THST_HOVER, PLND_*)",
        choices=("px4", "ardupilot"),
    )
    param: str | None = option(
        None,
        "a parameter set at start, NAME=VALUE of the profile's writable ones (as a parameter "
        "file loaded at boot), e.g. GUID_OPTIONS=8",
        str,
        repeatable=True,
    )

    def __post_init__(self) -> None:
        for name in ("mavlink_port", "remote_port", "camera_port", "gcs_port", "gcs_remote_port"):
            port = getattr(self, name)
            if not 0 <= port <= 65535:
                raise SitlError(f"{name} = {port}; expected a UDP port in [0, 65535]")
        positive = (
            "lockstep_timeout_s",
            "speed",
            "hold_timeout_s",
            "attitude_rate_hz",
            "imu_rate_hz",
            "distance_rate_hz",
            "groundtruth_rate_hz",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SitlError(f"{name} = {value}; expected a finite number > 0")
        if self.episodes < 1:
            raise SitlError(f"episodes = {self.episodes}; expected >= 1")
        if self.first_episode < 0:
            raise SitlError(f"first_episode = {self.first_episode}; expected >= 0")
        if self.episode_timeout_s is not None and not self.episode_timeout_s > 0:
            raise SitlError(f"episode_timeout_s = {self.episode_timeout_s}; expected > 0")
        for name in ("link_loss_prob", "link_duplicate_prob", "link_reorder_prob"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise SitlError(f"{name} = {value}; expected a probability in [0, 1]")
        for name in ("link_delay_ms", "link_jitter_ms", "link_cut_at_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0.0):
                raise SitlError(f"{name} = {value}; expected a finite number >= 0")
        if self.autopilot not in ("px4", "ardupilot"):
            raise SitlError(f"autopilot = {self.autopilot!r}; expected 'px4' or 'ardupilot'")
        try:
            parse_param_overrides(self.param, self.autopilot)
        except ValueError as exc:
            raise SitlError(str(exc)) from None
        if self.signing_key is not None:
            try:
                signing_key_bytes(self.signing_key)  # validates
            except SigningKeyError as exc:
                raise SitlError(f"signing_key: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, with the signing key redacted."""
        return redacted_dict(self)


def add_sitl_arguments(parser: argparse.ArgumentParser, **defaults: Any) -> None:
    """One ``--flag`` per :class:`SitlConfig` field, its help from the field's doc;
    ``defaults``: the command's own default of some fields (e.g. ``seed``)."""
    add_arguments(parser, SitlConfig, defaults=defaults)


def sitl_config_from_args(args: argparse.Namespace) -> SitlConfig:
    values = values_from_args(args, SitlConfig)
    if values.get("log_dir") == "":
        values["log_dir"] = None
    return SitlConfig(**values)


def initial_params(config: SitlConfig, hover_thrust_norm: float) -> AutopilotParams:
    """The profile's parameters at their defaults, then ``config.param`` (``--param``).

    Raises:
        SitlError: a value the parameter rejects (names it).
    """
    if config.autopilot == "ardupilot":
        params = ardupilot_params(hover_thrust_norm)
    else:
        params = AutopilotParams(mpc_thr_hover=hover_thrust_norm)
    for name, value in parse_param_overrides(config.param, config.autopilot):
        try:
            params = with_param(params, name, value, config.autopilot)
        except ValueError as exc:
            raise SitlError(f"--param {name}={value:g}: {exc}") from None
    return params
