"""``visland pad info``, ``visland pad print`` and ``visland pad check``: make the landing pad.

- ``info``: the pad's width in pixels against altitude, the highest altitude the model acquires
  it from, the start altitudes to fly from, and its luminance contrast against the ground
  (:mod:`tools.pad_info`);
- ``print``: the pad at true scale, a PDF tiled across pages or one PNG (:mod:`tools.pad_print`);
- ``check``: the model's CNN on a photograph of the laid-out pad taken from above — is it
  detected, and where (:func:`pad_check`);
- ``acquire``: from how high the model acquires the pad on a full-resolution camera, with and
  without the region of interest around the predicted pad (:mod:`tools.bench_roi`);
- ``error``: where the model's CNN places a scenario's pad (on a rover, a deck, any ground) per
  altitude band, in metres along the pad's axes (:mod:`tools.cnn_error`).

A pad is a pad file (``configs/pads/NAME.toml``) or the name of a shipped one (``paper``,
``helipad_1m``, ``quadrant_2m``). A bad pad file, ground image or photograph is an error naming
the file (and key), exit 2.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from tools.cli_args import config_from_args, json_command, print_result

__all__ = ["pad_check", "register_pad"]

_PadCommand = Callable[..., argparse.ArgumentParser]
"""``(name, help, default="paper") -> parser``: the subcommand ``pad NAME``, which takes the pad
its ``--pad`` names (default ``default``)."""


def _cmd_pad_info(args: argparse.Namespace) -> int:
    from tools.pad_info import format_info, pad_info, plot_info, resolve_pad

    info = pad_info(
        resolve_pad(args.pad),
        hfov_deg=args.camera_hfov_deg,
        resolution_px=args.resolution,
        ground=args.ground,
        families=not args.no_families,
    )
    if args.plot is not None:
        info["plot"] = str(plot_info(info, args.plot))
    print_result(info, args.json, format_info)
    if args.plot is not None and not args.json:
        print(f"wrote {info['plot']}")
    return 0


def _cmd_pad_print(args: argparse.Namespace) -> int:
    from tools.pad_info import resolve_pad
    from tools.pad_print import PAPER_NAMES, write_pdf, write_png

    pad = resolve_pad(args.pad)
    if args.png:
        out = args.out or Path(f"{pad.name}.png")
        rep = write_png(pad, out, args.dpi)
        w, h = pad.size_m
        print(
            f"wrote {rep.out}: pad {pad.name}, {w:g} x {h:g} m at {rep.image_dpi:g} dpi "
            "(print at this dpi for true scale)"
        )
        return 0
    out = args.out or Path(f"{pad.name}.pdf")
    rep = write_pdf(pad, out, args.paper)
    w, h = pad.size_m
    print(
        f"wrote {rep.out}: pad {pad.name}, {w:g} x {h:g} m on {rep.pages} pages of "
        f"{PAPER_NAMES[rep.paper]} {'landscape' if rep.landscape else 'portrait'} (page 1: the "
        f"assembly map; {rep.rows} rows x {rep.cols} columns of tiles; pad image "
        f"{rep.image_dpi:.0f} dpi). Print at 100 %: the 10 cm scale bar must measure 10 cm."
    )
    return 0


def _photo_to_net(path: Path, photo_hfov_deg: float | None, rotate_deg: int) -> Any:
    """The photograph as the camera gives it to the net: mono8, the centred 45° square (from
    the photo's horizontal FOV; without it the photo's centred square is taken as 45°), rotated
    so that the top is forward, area-resized to 128 x 128."""
    from companion.camera import CameraError, fit_to_policy, focal_px_from_fov
    from companion.contract import CAMERA_FOV_DEG
    from sitl_sim.errors import ConfigError
    from sitl_sim.render.ground import luma
    from sitl_sim.render.pads import read_image_rgb

    mono = luma(read_image_rgb(path, "IMAGE"))
    h, w = mono.shape
    try:
        if photo_hfov_deg is None:
            fx = min(h, w) / (2.0 * math.tan(math.radians(CAMERA_FOV_DEG) / 2.0))
        else:
            fx = focal_px_from_fov(w, photo_hfov_deg)
        return fit_to_policy(mono, fx, rotate_deg=rotate_deg)
    except CameraError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def pad_check(
    image: str | Path,
    checkpoint: str | Path | None = None,
    photo_hfov_deg: float | None = None,
    rotate_deg: int = 0,
) -> dict[str, Any]:
    """The model's CNN on a photograph of the pad from above: the pad's visibility probability,
    whether it is detected (at or above the checkpoint's ``visibility_threshold``) and its
    bearing in degrees right of and forward of (up in the photo) the image centre."""
    from companion.packaged import shipped_policy
    from companion.policy_net import load_policy

    ckpt = Path(checkpoint) if checkpoint is not None else shipped_policy()
    net_image = _photo_to_net(Path(image), photo_hfov_deg, rotate_deg)
    policy = load_policy(ckpt)
    if policy.privileged:
        from companion.policy_net import CheckpointError

        raise CheckpointError(f"{ckpt}: a privileged policy has no CNN; give a vision checkpoint")
    tan_right, tan_forward, logit = (float(v) for v in policy.perceive(net_image))
    prob = 1.0 / (1.0 + math.exp(-logit))
    threshold = float(policy.config.visibility_threshold)
    return {
        "image": str(image),
        "checkpoint": str(ckpt),
        "visibility": prob,
        "threshold": threshold,
        "detected": prob >= threshold,
        "bearing_right_deg": math.degrees(math.atan(tan_right)),
        "bearing_forward_deg": math.degrees(math.atan(tan_forward)),
    }


def _format_check(res: dict[str, Any], out: TextIO) -> None:
    verdict = "DETECTED" if res["detected"] else "NOT DETECTED"
    print(
        f"{res['image']}: pad {verdict}: visibility {res['visibility']:.3f} (threshold "
        f"{res['threshold']:.2f}, model {res['checkpoint']})",
        file=out,
    )
    if res["detected"]:
        print(
            f"bearing: {res['bearing_right_deg']:+.1f} deg right, "
            f"{res['bearing_forward_deg']:+.1f} deg forward of the image centre",
            file=out,
        )
    else:
        print(
            "the model does not see the pad here: more contrast with the ground (visland pad "
            "info --ground), a larger pad, or a photo from lower down",
            file=out,
        )


def _cmd_pad_check(args: argparse.Namespace) -> int:
    res = pad_check(args.image, args.checkpoint, args.photo_hfov_deg, args.rotate_deg)
    print_result(res, args.json, _format_check)
    return 0 if res["detected"] else 1


def _cmd_pad_acquire(args: argparse.Namespace) -> int:
    from tools.bench_roi import AcquireConfig, acquire, format_acquire

    width, _, height = args.camera.partition("x")
    if not (width.isdigit() and height.isdigit()):
        raise SystemExit(f"visland pad acquire: --camera {args.camera!r}; expected WIDTHxHEIGHT")
    cfg = config_from_args(
        AcquireConfig,
        args,
        width_px=int(width),
        height_px=int(height),
        hfov_deg=args.camera_hfov_deg,
        altitudes_m=tuple(args.altitudes),
        grounds=tuple(args.grounds),
    )
    print_result(acquire(cfg), args.json, format_acquire)
    return 0


def _cmd_pad_error(args: argparse.Namespace) -> int:
    from tools.cnn_error import ErrorConfig, cnn_error, format_error

    cfg = config_from_args(
        ErrorConfig,
        args,
        scenarios=tuple(args.scenario) if args.scenario else ErrorConfig().scenarios,
        bands_m=tuple(args.band) if args.band else ErrorConfig().bands_m,
    )
    print_result(cnn_error(cfg), args.json, format_error)
    return 0


def register_pad(sub: argparse._SubParsersAction) -> None:
    """Add ``pad`` (``info``, ``print``, ``check``, ``acquire``, ``error``) to the ``visland``
    subcommands."""
    from companion.contract import CAMERA_FOV_DEG, IMAGE_SIZE_PX
    from tools.pad_print import PAPERS

    pad_help = "pad file (configs/pads/NAME.toml) or a shipped pad's name"
    pd = sub.add_parser("pad", help="make the landing pad: info, print, check, acquire, error")
    pd_sub = pd.add_subparsers(dest="what", required=True)

    def pad_command(name: str, help: str, default: str = "paper") -> argparse.ArgumentParser:
        p = pd_sub.add_parser(name, help=help)
        p.add_argument("--pad", default=default, help=pad_help)
        return p

    pi = pad_command(
        "info",
        "the pad's width in pixels vs altitude, the highest altitude the model acquires it from, "
        "the start altitudes, its contrast against the ground",
    )
    pi.add_argument(
        "--camera-hfov-deg",
        type=float,
        default=CAMERA_FOV_DEG,
        help="the model's image: full horizontal field of view (degrees)",
    )
    pi.add_argument(
        "--resolution", type=int, default=IMAGE_SIZE_PX, help="the model's image width (px)"
    )
    pi.add_argument(
        "--ground", type=Path, default=None, help="a photo of your ground: contrast against it"
    )
    pi.add_argument(
        "--no-families",
        action="store_true",
        help="leave out the contrast against the simulator's ground families",
    )
    pi.add_argument("--plot", type=Path, default=None, help="also write the curve as a PNG")
    json_command(pi, _cmd_pad_info)
    pp = pad_command(
        "print",
        "the pad at true scale: a PDF tiled across pages (assembly map first, overlap, alignment "
        "marks, 10 cm scale bar), or one PNG for a print shop",
    )
    pp.add_argument(
        "--out", type=Path, default=None, help="output file (default: NAME.pdf or NAME.png)"
    )
    pp.add_argument("--paper", choices=sorted(PAPERS), default="a4", help="page size")
    pp.add_argument("--png", action="store_true", help="one PNG of the whole pad instead")
    pp.add_argument("--dpi", type=float, default=50.0, help="--png: dots per inch")
    pp.set_defaults(func=_cmd_pad_print)
    pc = pd_sub.add_parser(
        "check",
        help="run the model's CNN on a photo of the laid-out pad taken from above: detection "
        "and bearing; exit 1 if not detected",
    )
    pc.add_argument("image", type=Path, help="photograph (PNG/JPEG) taken straight down")
    pc.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="vision policy checkpoint (default: the shipped models/visland_vision.pt)",
    )
    pc.add_argument(
        "--photo-hfov-deg",
        type=float,
        default=None,
        help="the photo's horizontal field of view: its centred 45 deg is cropped, as the "
        "companion crops its camera (default: the photo's centred square is taken as 45 deg)",
    )
    pc.add_argument(
        "--rotate-deg",
        type=int,
        default=0,
        help="rotate the photo counter-clockwise (multiple of 90) so that its top is forward",
    )
    json_command(pc, _cmd_pad_check)
    _register_acquire(pad_command)
    _register_error(pd_sub)


def _register_acquire(pad_command: _PadCommand) -> None:
    from tools.bench_roi import AcquireConfig

    d = AcquireConfig()
    pa = pad_command(
        "acquire",
        "from how high the model acquires the pad on a full-resolution camera (rendered frames): "
        "the 45 deg crop (no ROI) vs the region of interest around the pad",
        d.pad,
    )
    pa.add_argument(
        "--checkpoint", default=None, help="vision checkpoint (default: the shipped model)"
    )
    pa.add_argument("--camera", default=f"{d.width_px}x{d.height_px}", help="WIDTHxHEIGHT px")
    pa.add_argument(
        "--camera-hfov-deg", type=float, default=d.hfov_deg, help="horizontal field of view"
    )
    pa.add_argument(
        "--altitudes", type=float, nargs="+", default=list(d.altitudes_m), help="metres"
    )
    pa.add_argument("--frames", type=int, default=d.frames, help="frames per altitude, ground")
    pa.add_argument("--grounds", nargs="+", default=list(d.grounds), help="nominal or families")
    pa.add_argument(
        "--span-px", type=float, default=d.span_px, help="the pad's width in the track window"
    )
    pa.add_argument("--tile-px", type=int, default=d.tile_px, help="search tile side (px)")
    pa.add_argument("--seed", type=int, default=d.seed, help="poses, noise and flights' seed")
    pa.add_argument(
        "--flights",
        type=int,
        default=d.flights,
        help="also fly this many episodes of --scenario on each camera (native, crop, roi)",
    )
    pa.add_argument("--scenario", default=d.scenario, help="--flights: the scenario file")
    json_command(pa, _cmd_pad_acquire)


def _register_error(pd_sub: argparse._SubParsersAction) -> None:
    from tools.cnn_error import ErrorConfig, parse_band

    def band(text: str) -> tuple[float, float]:
        try:
            return parse_band(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    d = ErrorConfig()
    pe = pd_sub.add_parser(  # no --pad: each scenario's [pad] is the pad
        "error",
        help="where the model's CNN places the pad of a scenario (a rover, a deck, a slope, any "
        "ground) per altitude band: share seen, error in metres, its bias along the pad's axes",
    )
    pe.add_argument(
        "--checkpoint", type=Path, default=None, help="vision checkpoint (default: the shipped)"
    )
    pe.add_argument(
        "--scenario",
        type=Path,
        action="append",
        help="scenario file (repeatable; default configs/scenario.toml): its [visual], [pad] "
        "and [terrain] are drawn as an episode's",
    )
    pe.add_argument(
        "--band",
        type=band,
        action="append",
        help="altitude band LO-HI in metres (repeatable; default 1-8 8-20 20-40 40-100)",
    )
    pe.add_argument("--frames", type=int, default=d.frames, help="frames per scenario and band")
    pe.add_argument("--seed", type=int, default=d.seed, help="500: the validation seed")
    pe.add_argument("--chunk", type=int, default=d.chunk, help="frames per drawn look and site")
    pe.add_argument("--workers", type=int, default=d.workers, help="rendering processes")
    json_command(pe, _cmd_pad_error)
