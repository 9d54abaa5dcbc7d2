"""Make the test ground images of this folder (``python configs/grounds/make_grounds.py``).

Each is a crop of a procedural terrain tile (``sitl_sim/render/terrain.py``, fixed family, seed
and sun) with a few man-made features painted on, saved small: a crop is not periodic, so the
mirrored tiling of ``[visual] ground_image`` shows at its edges.

- ``field_grass.jpg``   grass (seed 4), a dirt track across it; RGB JPEG, 640 px, ~0.08 m/px
- ``parking_lot.jpg``   asphalt (seed 9), white parking bays and a dashed lane; RGB JPEG, 0.05 m/px
- ``gravel_grey.png``   gravel (seed 2) with two tyre tracks; 8-bit grey PNG, 0.04 m/px
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from sitl_sim.render.ground import luma
from sitl_sim.render.terrain import Sun, terrain_map

HERE = Path(__file__).resolve().parent


def _crop(family: str, seed: int, sun: Sun, size: int) -> np.ndarray:
    return terrain_map(family, seed, sun).rgb[:size, :size].astype(np.float64)


def field_grass() -> np.ndarray:
    rgb = _crop("grass", 4, Sun(50.0, 120.0), 640)
    rows, cols = np.mgrid[0:640, 0:640]
    centre = 380 + 90 * np.sin(cols / 640 * 2 * np.pi * 0.8)  # a track winding across
    d = np.abs(rows - centre)
    track = np.clip((22 - d) / 4, 0, 1)[..., None]
    dirt = np.array([150.0, 124.0, 92.0]) * (0.9 + 0.1 * (rgb.mean(-1, keepdims=True) / 128))
    return rgb * (1 - track) + dirt * track


def parking_lot() -> np.ndarray:
    rgb = _crop("asphalt", 9, Sun(60.0, 200.0), 640)
    paint = np.array([222.0, 222.0, 214.0])
    mask = np.zeros((640, 640), bool)
    for x in range(40, 640, 50):  # bays 2.5 m wide, 5 m deep, lines 12 cm
        mask[60:160, x : x + 3] = True
        mask[480:580, x : x + 3] = True
    mask[158:161, 40:600] = mask[480:483, 40:600] = True
    for x in range(0, 640, 80):  # a dashed lane line between the rows
        mask[318:322, x : x + 40] = True
    rgb[mask] = 0.85 * paint + 0.15 * rgb[mask]
    return rgb


def gravel_grey() -> np.ndarray:
    rgb = _crop("gravel", 2, Sun(40.0, 300.0), 512)
    grey = luma(np.clip(rgb, 0, 255).astype(np.uint8)).astype(np.float64)
    cols = np.arange(512)[None, :]
    for c in (200, 245):  # tyre tracks 0.64 m wide, 1.8 m apart: compacted, darker
        grey *= np.where(np.abs(cols - c) < 8, 0.8, 1.0)
    return grey


def main() -> None:
    def u8(a: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(a), 0, 255).astype(np.uint8)

    Image.fromarray(u8(field_grass()), "RGB").save(HERE / "field_grass.jpg", quality=85)
    Image.fromarray(u8(parking_lot()), "RGB").save(HERE / "parking_lot.jpg", quality=85)
    Image.fromarray(u8(gravel_grey()), "L").save(HERE / "gravel_grey.png", optimize=True)


if __name__ == "__main__":
    main()
