"""The companion's configuration: :class:`CompanionConfig` (every field a ``--flag`` and a TOML
key of ``[companion]``), read from a TOML file and the command line.

**Defaults are the hardware template's** (``companion/assets/companion.toml``, installed with
the package: :func:`companion.packaged.template`): a serial link to PX4, an OpenCV camera, shadow
mode, engage only above 5 m, thrust ≤ 0.9, rates ≤ 2 / 1 rad/s. ``visland companion`` without
``--config`` loads that template, so the installed companion flies the shipped model beside it;
``--config FILE`` loads another; flags win over either. A relative ``policy`` (``*.pt``) or
``log_dir`` in a file is relative to that file's folder, not to the working directory. The
simulator's launches (``training.companion_process.sim_companion_args``) pass the flight and
safety settings they fly with (:class:`~companion.flight.OffboardConfig`'s and
:class:`~companion.safety.SafetyConfig`'s own defaults) explicitly.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from companion import options
from companion.camera import CameraError, check_intrinsics, open_camera
from companion.files import read_toml
from companion.flight import OffboardConfig
from companion.link import PROFILES, MavlinkLink
from companion.options import option, redacted_dict
from companion.packaged import template
from companion.safety import SafetyConfig
from companion.states import TouchdownAction
from companion.table import ConfigError, Section, check_tables, read_values

__all__ = [
    "CompanionConfig",
    "CompanionError",
    "add_arguments",
    "config_from_args",
    "load_toml",
    "open_camera_and_link",
    "open_configured_camera",
    "open_configured_link",
]


class CompanionError(ConfigError):
    """A configuration or start-up error (names the file/field and the expected value)."""


_FLIGHT = {f.name: f.default for f in dataclasses.fields(OffboardConfig)}
"""OffboardConfig's defaults: the flight fields below take theirs from here."""
_SAFETY = {f.name: f.default for f in dataclasses.fields(SafetyConfig)}
"""SafetyConfig's defaults (seconds, per-axis tuple): the safety fields below convert them."""


@dataclass(frozen=True)
class CompanionConfig(Section):
    """Everything ``visland companion`` takes; each field is a ``--flag`` and a key of the
    ``[companion]`` table, read and range-checked by the one table reader
    (:mod:`companion.table`; ``source``: where it was read, for errors)."""

    SECTION: ClassVar[str] = "companion"
    ERROR: ClassVar[type[ConfigError]] = CompanionError

    connect: str = option(
        "serial:/dev/ttyAMA0:921600",
        "MAVLink connection: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, /dev/ttyX or "
        "serial:/dev/ttyX:BAUD",
    )
    baud: int = option(921_600, "serial baud rate", unit="bit/s", lo=1)
    autopilot: str = option("px4", "autopilot profile", choices=tuple(PROFILES))
    camera: str = option(
        "opencv:0", "camera: opencv:DEVICE|FILE|PIPELINE, udp:HOST:PORT (SITL), mcap:LOG"
    )
    camera_fx_px: float | None = option(
        None, "real camera: focal length fx", float, unit="px", lo=0.0, lo_open=True
    )
    camera_hfov_deg: float | None = option(
        62.2,
        "real camera: horizontal FOV (no intrinsics; the default is the Raspberry Pi Camera "
        "Module 2's; a --camera-fx-px flag replaces it)",
        float,
        unit="deg",
    )
    camera_cx_px: float | None = option(
        None, "real camera: principal point cx (default: centre)", float, unit="px"
    )
    camera_cy_px: float | None = option(
        None, "real camera: principal point cy (default: centre)", float, unit="px"
    )
    camera_rotate_deg: int = option(
        0, "real camera: rotation (CCW) so image top = body forward", unit="deg"
    )
    camera_rate_hz: float = option(
        10.0,
        "real camera: frames handed to the policy per second (its 10 Hz control rate)",
        unit="Hz",
        lo=0.0,
        lo_open=True,
    )
    camera_roi: bool = option(
        False,
        "real camera: cut the policy's image from the full-resolution frame around the pad the "
        "estimator predicts, resampled to 128 px (companion.roi; offboard and landing-target "
        "modes), instead of the centred 45 deg crop",
    )
    camera_roi_pad_m: float = option(
        1.0,
        "camera_roi: the pad's width the window is sized for",
        unit="m",
        lo=0.0,
        hi=100.0,
        lo_open=True,
    )
    camera_roi_span_px: float = option(
        24.0,
        "camera_roi: the pad's width in the policy's 128 px image while tracking",
        unit="px",
        lo=0.0,
        hi=128.0,
        lo_open=True,
    )
    mode: str = option(
        "offboard",
        "offboard: fly the policy's commands (SET_ATTITUDE_TARGET); landing-target: run only "
        "its camera pad estimator, stream LANDING_TARGET and let the autopilot's precision "
        "land (PX4 AUTO.PRECLAND, ArduPilot LAND + PLND) fly",
        choices=("offboard", "landing-target"),
    )
    target_timeout_s: float = option(
        1.0,
        "landing-target mode: stop sending this long after the pad was last seen",
        unit="s",
        lo=0.0,
        lo_open=True,
    )
    policy: str = option(
        "",
        "policy checkpoint (visland companion also takes expert | cascade); unset: the config's "
        "(the template's: the shipped model installed with the package)",
    )
    estimator: str = option(
        "",
        "the checkpoint's estimator and landing-guard values replaced, KEY=VALUE (the keys of "
        "visland eval --estimator: e.g. land_floor_m=15, pad_timeout_s=60, search_altitude_m="
        "40); '' = the checkpoint's own",
        repeatable=True,
    )
    runtime: str = option(
        "auto",
        "learned policy backend: onnx (ONNX Runtime on the visland export-onnx graphs beside "
        "the checkpoint; no torch needed), torch, or auto (onnx when onnxruntime is installed "
        "and the export is there, else torch)",
        choices=("auto", "torch", "onnx"),
    )
    torch_threads: int = option(1, "intra-op threads for the policy (torch or ONNX Runtime)", lo=1)
    shadow: bool = option(True, "compute and log every command; send no setpoint, no mode change")
    bench: bool = option(
        False,
        "shadow on the bench (props off, on the ground): implies --shadow and logs what the "
        "policy would command from the first fresh frame, disarmed and at any range",
    )
    arm: bool = option(
        _FLIGHT["arm"], "arm when disarmed (SITL demo only; on hardware the pilot arms)"
    )
    flights: int = option(1, "flights to fly before exiting (0: until stopped)", lo=0)
    signing_key: str | None = option(
        None, "MAVLink 2 signing key: 64 hex digits or a passphrase", str
    )
    sysid: int = option(0, "our MAVLink system id (0: the autopilot's)", lo=0, hi=255)
    max_age_ms: float = option(
        _SAFETY["max_age_s"] * 1000.0,
        "failsafe when camera or telemetry is older than this",
        unit="ms",
        lo=0.0,
        lo_open=True,
    )
    near_ground_m: float = option(
        _SAFETY["near_ground_m"], "below this, no valid range = failsafe", unit="m"
    )
    thrust_min: float = option(_SAFETY["thrust_min"], "thrust clamp, low")
    thrust_max: float = option(0.9, "thrust clamp, high")
    max_rate_rp_rad_s: float = option(2.0, "roll/pitch rate clamp", unit="rad/s")
    max_rate_yaw_rad_s: float = option(1.0, "yaw rate clamp", unit="rad/s")
    prestream_s: float = option(
        _FLIGHT["prestream_s"],
        "neutral setpoints streamed before requesting OFFBOARD",
        unit="s",
    )
    engage_min_range_m: float = option(5.0, "engage only above this radar range", unit="m")
    engage_in_air: bool = option(
        False,
        "take control of a vehicle that is already armed when the companion first hears it (a "
        "companion restarted in the air): only on the operator's word; by default it waits for "
        "a disarm. The simulator's launches pass it (each episode starts in the air)",
    )
    touchdown_range_m: float = option(
        _FLIGHT["touchdown_range_m"],
        "radar range at or below which the vehicle is down",
        unit="m",
    )
    on_touchdown: str = option(
        _FLIGHT["on_touchdown"].value,
        "after touchdown",
        str,
        choices=tuple(action.value for action in TouchdownAction),
    )
    on_exit: str = option("land", "mode requested on SIGINT/SIGTERM", choices=("land", "hold"))
    hover_thrust: float = option(
        _FLIGHT["hover_thrust"], "neutral thrust if the autopilot does not report it"
    )
    link_timeout_s: float = option(
        3.0, "no autopilot HEARTBEAT this long = link lost", unit="s", lo=0.0, lo_open=True
    )
    log_dir: str | None = option(
        "/var/lib/visland/flights", "folder for one MCAP log per flight ('': a temporary one)", str
    )
    max_wall_s: float | None = option(
        None, "exit after this many seconds (safety net)", float, unit="s", lo=0.0, lo_open=True
    )
    live: str = option(
        "",
        "serve a live view in Foxglove on [HOST:]PORT (e.g. 8765 on 127.0.0.1, 0.0.0.0:8765 for "
        "the field laptop; pip install 'visland[live]'); '' = off",
    )

    log_scene: str = option(
        "auto",
        "write the live view's picture (scene, transforms, camera annotations) into each flight "
        "log as it flies, so a log opens in Foxglove as the live view shows it: 'auto' where "
        "foxglove-sdk is installed ('visland[live]'), 'on' (an error without it), 'off' (add it "
        "later with visland log scene)",
        choices=("auto", "on", "off"),
    )

    def __post_init__(self) -> None:
        super().__post_init__()  # each key's type and range (companion.table)
        if self.live:
            from companion.live import parse_live

            try:
                parse_live(self.live)
            except ValueError as exc:
                raise CompanionError(str(exc)) from None
        if self.camera_rotate_deg % 90:
            raise CompanionError(f"camera_rotate_deg = {self.camera_rotate_deg}; a multiple of 90")
        self.estimator_settings()  # a bad --estimator stops here, before a link opens
        if self.camera.startswith("opencv:"):
            try:
                check_intrinsics(self.camera_fx_px, self.camera_hfov_deg)
            except CameraError as exc:
                raise CompanionError(f"camera {self.camera!r}: {exc}") from None
        if self.camera_roi and not self.camera.startswith("opencv:"):
            raise CompanionError(
                f"camera_roi = true: expected an opencv: camera, got camera = {self.camera!r} "
                "(SITL frames are 128 px already)"
            )

    def estimator_settings(self) -> dict[str, Any]:
        """``estimator`` as (key, value) pairs checked against a network's config.

        Raises:
            CompanionError: a bad key or value (names it).
        """
        from companion.policy_net.config import CheckpointError, NetConfig

        try:
            settings = NetConfig.parse_settings(self.estimator)
            NetConfig().with_settings(settings)  # ranges and the checks between keys
        except CheckpointError as exc:
            raise CompanionError(f"{self.source}: [companion] estimator: {exc}") from None
        return settings

    def with_estimator(self, policy: Any) -> Any:
        """``policy`` flying with :meth:`estimator_settings` (itself when there are none).

        Raises:
            CompanionError: settings for a policy without an estimator (expert, cascade), or
                a value the checkpoint's own config refuses.
        """
        settings = self.estimator_settings()
        if not settings:
            return policy
        if not callable(getattr(policy, "with_settings", None)):
            raise CompanionError(
                f"estimator = {self.estimator!r}: {self.policy!r} has no estimator (a "
                "checkpoint has)"
            )
        from companion.policy_net.config import CheckpointError

        try:
            return policy.with_settings(settings)
        except CheckpointError as exc:
            raise CompanionError(f"estimator = {self.estimator!r}: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, with the signing key redacted."""
        return redacted_dict(self)

    def safety_config(self) -> SafetyConfig:
        """The safety monitor's limits (milliseconds to seconds, per-axis rate clamp).

        Raises:
            companion.safety.SafetyError: a limit out of range.
        """
        return SafetyConfig(
            max_age_s=self.max_age_ms / 1000.0,
            near_ground_m=self.near_ground_m,
            thrust_min=self.thrust_min,
            thrust_max=self.thrust_max,
            max_rate_rad_s=(
                self.max_rate_rp_rad_s,
                self.max_rate_rp_rad_s,
                self.max_rate_yaw_rad_s,
            ),
        )

    def offboard_config(self) -> OffboardConfig:
        """The state machine's settings (those not set here keep OffboardConfig's defaults).

        Raises:
            ValueError: a setting out of range.
        """
        return OffboardConfig(
            shadow=self.shadow or self.bench,
            bench=self.bench,
            arm=self.arm,
            prestream_s=self.prestream_s,
            engage_min_range_m=self.engage_min_range_m,
            touchdown_range_m=self.touchdown_range_m,
            on_touchdown=self.on_touchdown,  # OffboardConfig makes it a TouchdownAction
            hover_thrust=self.hover_thrust,
        )


def _relative_to(path: Path, table: dict[str, Any]) -> dict[str, Any]:
    """``table`` with a relative ``policy`` checkpoint (``*.pt``) and ``log_dir`` made relative
    to ``path``'s folder (a name such as ``expert`` stays a name)."""
    out = dict(table)
    policy = out.get("policy")
    if policy and Path(policy).suffix == ".pt" and not Path(policy).is_absolute():
        out["policy"] = str(path.parent / policy)
    log_dir = out.get("log_dir")
    if log_dir and not Path(log_dir).is_absolute():
        out["log_dir"] = str(path.parent / log_dir)
    return out


def load_toml(path: str | Path) -> dict[str, Any]:
    """The ``[companion]`` table of a TOML file, checked against the config's fields; a
    relative ``policy`` / ``log_dir`` is made relative to the file's folder.

    Raises:
        CompanionError: the file is missing or not TOML, or the table is missing or wrong.
    """
    path = Path(path)
    data = read_toml(path, CompanionError)
    check_tables(data, str(path), ("companion",), ("companion",), CompanionError)
    values = read_values(CompanionConfig, data["companion"], str(path))
    return _relative_to(path.absolute(), values)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--config``, ``--replay``, ``--check`` and one ``--flag`` per :class:`CompanionConfig`
    field."""
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="TOML file ([companion] table) (default: the hardware template installed with the "
        "package, companion/assets/companion.toml: shadow on, the shipped model)",
    )
    parser.add_argument(
        "--replay", type=Path, default=None, help="replay a companion log in shadow mode"
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="bench check on the ground: print camera frames, pad detection and bearing live, "
        "the autopilot link, its telemetry and parameters; never sends a setpoint or a mode "
        "change (stop with Ctrl-C or --max-wall-s)",
    )
    parser.add_argument("--json", action="store_true", help="(accepted; the report is JSON)")
    options.add_arguments(parser, CompanionConfig, unset_is_none=True)  # None: not given


def config_from_args(args: argparse.Namespace) -> CompanionConfig:
    """Defaults, then the TOML file (``--config``, else the installed template), then the
    flags. A ``--camera-fx-px`` flag replaces the file's ``camera_hfov_deg`` (the camera's
    intrinsics come from one place).

    Raises:
        CompanionError: naming the file and key, or the field and its expected value.
        companion.packaged.PackageDataError: no ``--config`` and no template installed.
    """
    path = args.config if args.config is not None else template()
    values: dict[str, Any] = dict(load_toml(path))
    flags = options.values_from_args(args, CompanionConfig)
    if "camera_fx_px" in flags and "camera_hfov_deg" not in flags:
        values["camera_hfov_deg"] = None
    values.update(flags)
    if values.get("log_dir") == "":
        values["log_dir"] = None
    where = f"{path}, with flags {sorted(flags)}" if flags else str(path)
    return CompanionConfig(**values, source=where)


def open_configured_camera(cfg: CompanionConfig):
    """The camera source ``cfg.camera`` names, with a real camera's intrinsics and rate.

    Raises:
        companion.camera.CameraError: cannot open it (names the source).
    """
    opts: dict[str, Any] = {}
    if cfg.camera.startswith("opencv:"):
        opts = {
            "fx_px": cfg.camera_fx_px,
            "hfov_deg": cfg.camera_hfov_deg,
            "cx_px": cfg.camera_cx_px,
            "cy_px": cfg.camera_cy_px,
            "rotate_deg": cfg.camera_rotate_deg,
            "rate_hz": cfg.camera_rate_hz,
        }
    if cfg.camera_roi:  # full frames, cut to the policy's window (RoiCameraSource.follow)
        from companion.roi import RoiCameraSource

        pad, span = cfg.camera_roi_pad_m, cfg.camera_roi_span_px
        return RoiCameraSource(cfg.camera[len("opencv:") :], pad_m=pad, span_px=span, **opts)
    return open_camera(cfg.camera, **opts)


def open_configured_link(cfg: CompanionConfig) -> MavlinkLink:
    """The MAVLink link ``cfg.connect`` names (profile, system id, signing, timeout).

    Raises:
        companion.link.LinkError: cannot open it (names the connection).
    """
    from companion.contract.signing import signing_key_bytes

    return MavlinkLink(
        cfg.connect,
        baud=cfg.baud,
        profile=PROFILES[cfg.autopilot],
        sysid=cfg.sysid or None,
        signing_key=signing_key_bytes(cfg.signing_key) if cfg.signing_key else None,
        link_timeout_s=cfg.link_timeout_s,
    )


def open_camera_and_link(cfg: CompanionConfig) -> tuple[Any, MavlinkLink]:
    """The configured camera, then the link; the camera is closed again when the link cannot
    open, so a failed start leaves no device held.

    Raises:
        companion.camera.CameraError: cannot open the camera.
        companion.link.LinkError: cannot open the link.
    """
    with contextlib.ExitStack() as opened:
        camera = open_configured_camera(cfg)
        opened.callback(camera.close)
        link = open_configured_link(cfg)
        opened.pop_all()
    return camera, link
