"""``visland pad info``: what a pad design gives the model — its width in pixels against
altitude, the highest altitude the model can acquire it from, the start altitudes a scenario (and
a real flight) should use, and its luminance contrast against the ground it will lie on.

**Acquiring a pad** is defined by a pixel width measured from the shipped model on the paper
pad: the model acquires the 4 m paper pad from the scenario's start altitudes, 75-100 m
(``configs/scenario.toml``, ``[initial_state] altitude_m``), so at the top of that range, 100 m,
the pad spans :data:`ACQUIRE_PX` = 128 x 4 / (2 x 100 x tan 22.5°) = 6.18 pixels of the
model's 128 px, 45° image. A pad of width ``w`` is taken as acquirable up to the altitude where
it spans that many pixels (25 m per metre of pad at 128 px / 45°), and a flight should start
between :data:`START_FRACTION` of that altitude and that altitude — the scenario's 75-100 m.
The rule lives in :mod:`sitl_sim.render.pads` (re-exported here), where training reads it too.

**Contrast**: the camera is mono8, so a pad's hue counts for nothing, only its luminance (the
project's BT.601 :func:`sitl_sim.render.ground.luma`). Each part of the pad
(:meth:`~sitl_sim.render.pads.PadDesign.parts`) is compared with the ground's median luma; a
part within :data:`VANISH_LEVELS` grey levels of it vanishes into the ground (the paper pad's
green square on sand: only its 0.6 m cross is left to see). Grounds: an image of the user's own
ground (``--ground``) and the simulator's ground families (:mod:`sitl_sim.render.terrain`, lit
by an overhead sun; ``nominal`` is the original ground).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from sitl_sim.errors import ConfigError
from sitl_sim.render.pads import (
    ACQUIRE_PX,
    REFERENCE,
    START_FRACTION,
    PadDesign,
    acquire_altitude_m,
    builtin_pad_paths,
    fill_altitude_m,
    load_pad,
    pad_width_px,
    read_image_rgb,
    start_altitudes_m,
)

__all__ = [
    "ACQUIRE_PX",
    "REFERENCE",
    "START_FRACTION",
    "VANISH_LEVELS",
    "acquire_altitude_m",
    "contrast_rows",
    "family_lumas",
    "format_info",
    "ground_luma",
    "pad_info",
    "pad_width_px",
    "plot_info",
    "resolve_pad",
    "start_altitudes_m",
]

VANISH_LEVELS = 16.0
"""A part of the pad whose luma is within this many grey levels (of 255) of the ground's median
vanishes into the ground: about 6 % of full scale, the half-width of the 10-90 % luma spread of
the simulator's ground textures (12-16 levels), so such a part is lost in the ground's own
texture."""

GROUND_SEED = 0
"""The texture seed of the ground families' samples."""


def resolve_pad(spec: str | Path) -> PadDesign:
    """A pad file, or the name of a shipped one (``paper``, ``helipad_1m``...)."""
    text = str(spec)
    shipped = builtin_pad_paths()
    if text in shipped and not Path(text).exists():
        return load_pad(shipped[text])
    return load_pad(text)


# --------------------------------------------------------------------------- grounds


def ground_luma(path: str | Path) -> np.ndarray:
    """The mono8 luma of a ground photograph (any image Pillow reads).

    Raises:
        ConfigError: missing or unreadable file (names the file).
    """
    from sitl_sim.render.ground import luma

    return luma(read_image_rgb(Path(path), "--ground"))


def family_lumas() -> dict[str, np.ndarray]:
    """The mono8 texture of every ground the simulator draws: ``nominal`` (the part of the
    original texture on the ground) and each terrain family (seed :data:`GROUND_SEED`, sun
    overhead: the light level the renderer multiplies pad and ground by alike is left out)."""
    from sitl_sim.render.ground import nominal_ground
    from sitl_sim.render.terrain import FAMILIES, Sun, terrain_map

    nominal = nominal_ground().mono
    used = nominal.shape[0] // 4  # the box's top face: the last quarter in u and v
    out = {"nominal": nominal[-used:, -used:]}
    for family in FAMILIES:
        out[family] = terrain_map(family, GROUND_SEED, Sun(90.0, 0.0)).mono
    return out


def contrast_rows(pad: PadDesign, grounds: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """One row per ground: its median luma, its 10-90 % spread, and per part of the pad the luma
    difference (part - ground median) and whether the part vanishes (``|diff| <
    VANISH_LEVELS``)."""
    parts = pad.parts()
    rows = []
    for name, mono in grounds.items():
        lo, median, hi = (float(v) for v in np.percentile(mono, [10, 50, 90]))
        diffs = {part: float(level) - median for part, level in parts}
        rows.append(
            {
                "ground": name,
                "median_luma": median,
                "spread_10_90": [lo, hi],
                "contrast": diffs,
                "vanishes": [p for p, d in diffs.items() if abs(d) < VANISH_LEVELS],
            }
        )
    return rows


def _warnings(pad: PadDesign, rows: list[dict[str, Any]]) -> list[str]:
    names = [p for p, _ in pad.parts()]
    out = []
    for row in rows:
        gone = row["vanishes"]
        if not gone:
            continue
        left = [p for p in names if p not in gone]
        what = ", ".join(gone)
        if left:
            out.append(
                f"on {row['ground']}: the pad's {what} vanishes into the ground (within "
                f"{VANISH_LEVELS:g} levels of its luma {row['median_luma']:.0f}); only its "
                f"{', '.join(left)} is left to see"
            )
        else:
            out.append(
                f"on {row['ground']}: the whole pad vanishes into the ground (every part within "
                f"{VANISH_LEVELS:g} levels of its luma {row['median_luma']:.0f}): pick a pad "
                "that contrasts with it"
            )
    return out


# --------------------------------------------------------------------------- the report


def _curve_altitudes(acquire_m: float, fill_m: float) -> list[float]:
    """Round altitudes from where the pad fills the view to 1.5 x the acquire altitude, with
    the acquire altitude and the start range's bottom among them."""
    steps = [1, 2, 3, 5, 7.5, 10, 15, 20, 25, 30, 40, 50, 60, 75, 100, 125, 150, 200, 300, 400]
    picks = {a for a in steps if fill_m <= a <= 1.5 * acquire_m}
    picks |= {round(acquire_m, 2), round(START_FRACTION * acquire_m, 2)}
    return sorted(picks)


def pad_info(
    pad: PadDesign,
    hfov_deg: float = 45.0,
    resolution_px: int = 128,
    ground: str | Path | None = None,
    families: bool = True,
) -> dict[str, Any]:
    """The envelope of ``pad`` for this camera, and its contrast against ``ground`` (an image)
    and the simulator's ground families."""
    if not (math.isfinite(hfov_deg) and 0.0 < hfov_deg < 180.0):
        raise ConfigError(f"--camera-hfov-deg: expected in (0, 180), got {hfov_deg}")
    if resolution_px < 1:
        raise ConfigError(f"--resolution: expected a pixel count >= 1, got {resolution_px}")
    width_m = float(min(pad.size_m))
    acquire = acquire_altitude_m(width_m, hfov_deg, resolution_px)
    fill = fill_altitude_m(width_m, hfov_deg)
    grounds: dict[str, np.ndarray] = {}
    if ground is not None:
        grounds[Path(ground).name] = ground_luma(ground)
    if families:
        grounds.update(family_lumas())
    rows = contrast_rows(pad, grounds)
    return {
        "pad": pad.name,
        "file": str(pad.path) if pad.path is not None else None,
        "size_m": [float(v) for v in pad.size_m],
        "width_m": width_m,
        "camera": {"hfov_deg": hfov_deg, "resolution_px": resolution_px},
        "acquire_px": ACQUIRE_PX,
        "acquire_px_reference": (
            f"the shipped model acquires the {REFERENCE['pad_m']:g} m paper pad from the "
            f"scenario's 75-100 m start altitudes: {ACQUIRE_PX:.2f} px wide at "
            f"{REFERENCE['altitude_m']:g} m with {REFERENCE['resolution_px']} px / "
            f"{REFERENCE['hfov_deg']:g} deg"
        ),
        "acquire_altitude_m": acquire,
        "start_altitude_m": list(start_altitudes_m(width_m, hfov_deg, resolution_px)),
        "fill_altitude_m": fill,
        "curve": [
            {"altitude_m": a, "width_px": pad_width_px(width_m, a, hfov_deg, resolution_px)}
            for a in _curve_altitudes(acquire, fill)
        ],
        "parts": [{"name": n, "luma": float(v)} for n, v in pad.parts()],
        "vanish_levels": VANISH_LEVELS,
        "contrast": rows,
        "warnings": _warnings(pad, rows),
    }


def format_info(info: dict[str, Any], out: TextIO) -> None:
    """``info`` as the human-readable report."""
    w, h = info["size_m"]
    cam = info["camera"]
    lo, hi = info["start_altitude_m"]
    where = f" ({info['file']})" if info["file"] else ""
    print(f"pad {info['pad']}: {w:g} x {h:g} m{where}", file=out)
    print(
        f"camera: {cam['resolution_px']} px across {cam['hfov_deg']:g} deg (the model's input)",
        file=out,
    )
    print(
        f"acquire threshold: {info['acquire_px']:.2f} px of pad width "
        f"({info['acquire_px_reference']})",
        file=out,
    )
    print(f"highest altitude to acquire it: {info['acquire_altitude_m']:.1f} m", file=out)
    print(
        f"start altitudes: {lo:.1f} - {hi:.1f} m (scenario [initial_state] altitude_m = "
        f"[{lo:.1f}, {hi:.1f}])",
        file=out,
    )
    print(f"the pad fills the image at {info['fill_altitude_m']:.2f} m", file=out)
    print(f"{'altitude (m)':>12}  {'width (px)':>10}  model", file=out)
    for row in info["curve"]:
        sees = row["width_px"] >= info["acquire_px"] - 1e-9
        note = "acquires it" if sees else "too small to acquire"
        if lo - 1e-6 <= row["altitude_m"] <= hi + 1e-6:
            note += " (start altitudes)"
        print(f"{row['altitude_m']:12.2f}  {row['width_px']:10.2f}  {note}", file=out)
    if info["contrast"]:
        parts = [p["name"] for p in info["parts"]]
        levels = ", ".join(f"{p['name']} {p['luma']:.0f}" for p in info["parts"])
        print(
            f"contrast, mono8 luma (0-255): part - ground median; '!' = vanishes (within "
            f"{info['vanish_levels']:g} levels). Pad: {levels}",
            file=out,
        )
        width = max(12, *(len(r["ground"]) for r in info["contrast"]))
        cols = {p: max(8, len(p) + 1) for p in parts}
        head = "".join(f"{p:>{cols[p]}}  " for p in parts)
        print(f"{'ground':<{width}}  {'median':>6}{head}", file=out)
        for row in info["contrast"]:
            cells = "".join(
                f"{row['contrast'][p]:+{cols[p]}.0f}{' !' if p in row['vanishes'] else '  '}"
                for p in parts
            )
            print(f"{row['ground']:<{width}}  {row['median_luma']:6.0f}{cells}", file=out)
    for line in info["warnings"]:
        print(f"warning: {line}", file=out)


def plot_info(info: dict[str, Any], out: str | Path) -> Path:
    """The report as a PNG: width in pixels against altitude (the acquire threshold, the start
    altitudes) and, where contrast was measured, each part's contrast per ground."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    width_m = info["width_m"]
    cam = info["camera"]
    top = max(1.5 * info["acquire_altitude_m"], 2.0 * info["fill_altitude_m"])
    alt = np.linspace(max(info["fill_altitude_m"], top / 200.0), top, 400)
    px = pad_width_px(width_m, alt, cam["hfov_deg"], cam["resolution_px"])
    panels = 2 if info["contrast"] else 1
    fig, axes = plt.subplots(1, panels, figsize=(6.5 * panels, 4.5), squeeze=False)
    ax = axes[0, 0]
    ax.plot(alt, px, color="C0", label=f"{info['pad']} ({width_m:g} m)")
    ax.axhline(
        info["acquire_px"], color="C3", ls="--", label=f"acquire: {info['acquire_px']:.2f} px"
    )
    lo, hi = info["start_altitude_m"]
    ax.axvspan(lo, hi, color="C2", alpha=0.2, label=f"start altitudes {lo:.1f}-{hi:.1f} m")
    ax.set_yscale("log")
    ax.set_xlabel("altitude (m)")
    ax.set_ylabel(f"pad width (px of {cam['resolution_px']}, {cam['hfov_deg']:g} deg)")
    ax.set_title(f"pad {info['pad']}: width in the model's image")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    if panels == 2:
        ax = axes[0, 1]
        parts = [p["name"] for p in info["parts"]]
        grounds = [r["ground"] for r in info["contrast"]]
        x = np.arange(len(grounds))
        bar = 0.8 / max(1, len(parts))
        for k, part in enumerate(parts):
            vals = [abs(r["contrast"][part]) for r in info["contrast"]]
            ax.bar(x + (k - (len(parts) - 1) / 2) * bar, vals, bar, label=part)
        ax.axhline(info["vanish_levels"], color="C3", ls="--", label="vanishes below")
        ax.set_xticks(x, grounds, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel("|part luma - ground median| (levels)")
        ax.set_title("luminance contrast against the ground (mono8)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
