"""What both renderers draw of a landing site (:mod:`sitl_sim.site`), built once per episode.

A site changes the ground in two ways, and both renderers read the same textures so that a test
can hold them to the same image:

- **the slope** tilts the ground plane: the ground texture is lit as the tilted plane is
  (:attr:`SiteLook.base`: the episode's ground x one Lambert factor relative to flat ground);
- **relief, craters and rocks** lie within :data:`~sitl_sim.site.terrain.SITE_HALF_M` of the
  pad's start: one composite texture covers that square (:attr:`SiteLook.region`, texels of
  :data:`REGION_TEXEL_M`): the episode's ground resampled there, rock and crater albedo on it,
  lit by the sun over the full surface (slope + relief + rocks: Lambert relative to flat ground,
  the relief's cast shadows from a march on its 1 m grid, each rock's cast shadow from a ray
  toward the sun against its ellipsoid), and :attr:`SiteLook.rock_level`, each texel's rock
  height above the ground quantised to 2..255 (1: bare ground of the region).

pybullet draws the region as a mesh on the heightfield and each rock as a dome mesh, both
textured with the composite (so a rock seen from the side shows the colours of its top view);
the fast renderer warps the composite onto the relief and re-draws the rocks in a few height
slices for parallax. The vehicle's faces are lit by :func:`face_light`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sitl_sim.render.ground import GroundMap
from sitl_sim.render.terrain import AMBIENT, DIFFUSE, Sun
from sitl_sim.site.site import Site
from sitl_sim.site.terrain import GRID_M, SITE_HALF_M, Terrain

__all__ = ["REGION_TEXEL_M", "SiteLook", "face_light"]

REGION_TEXEL_M = 0.08
_ROCK_MIN_M = 0.004  # a texel is rock where the rock stands this much above the ground
_OVERHEAD = Sun(90.0, 0.0)


def _lambert(normal_up_ned: np.ndarray, sun: Sun) -> float:
    s = sun.toward_ned
    return max(0.0, float(normal_up_ned @ s))


def face_light(normal_ned, sun: Sun | None) -> float:
    """Light on a face of outward ``normal_ned`` relative to flat ground under ``sun`` (the
    renderers' convention: the camera applies the flat-ground level to the whole image)."""
    sun = sun or _OVERHEAD
    return (AMBIENT + DIFFUSE * _lambert(np.asarray(normal_ned, dtype=float), sun)) / sun.flat_light


class SiteLook:
    """The textures of one site under one sun (see the module docstring)."""

    def __init__(self, ground: GroundMap, site: Site, sun: Sun | None = None) -> None:
        self.site = site
        self.sun = sun or _OVERHEAD
        terrain = site.terrain
        self.base = ground
        """The ground outside the region, lit as the slope plane is."""
        if terrain is not None and terrain.slope_deg > 0.0:
            gn, ge = terrain.gradient
            up = np.array([-gn, -ge, -1.0]) / math.sqrt(gn * gn + ge * ge + 1.0)
            factor = face_light(up, self.sun)
            rgb = np.clip(np.rint(ground.rgb.astype(np.float32) * factor), 0, 255).astype(np.uint8)
            self.base = GroundMap(
                rgb=rgb,
                texel_to_ne=ground.texel_to_ne,
                periodic=ground.periodic,
                name=f"{ground.name}/slope",
                tile_m=ground.tile_m,
            )
        self.region: GroundMap | None = None
        """The composite texture over the relief, craters and rocks (None: there are none)."""
        self.rock_level: np.ndarray | None = None
        """uint8 per region texel: 1 bare ground, 2..255 rock height up to :attr:`rock_max_m`."""
        self.rock_max_m = 0.0
        if terrain is not None and (terrain.heights is not None or len(terrain.rocks)):
            self._build_region(ground, terrain)

    @property
    def heightfield(self) -> bool:
        """Whether the ground within the region has relief or craters (not only a plane)."""
        return self.site.terrain is not None and self.site.terrain.heights is not None

    # ------------------------------------------------------------------ the region's texture

    def _build_region(self, ground: GroundMap, terrain: Terrain) -> None:
        s, half = REGION_TEXEL_M, SITE_HALF_M
        size = round(2 * half / s)
        # texel (col, row) centre: north = -L + (col + .5) s, east = L - (row + .5) s
        to_ne = np.array([[s, 0.0, -half + 0.5 * s], [0.0, -s, half - 0.5 * s], [0.0, 0.0, 1.0]])
        inverse = np.linalg.inv(ground.texel_to_ne) @ to_ne
        albedo = cv2.warpAffine(
            ground.rgb,
            inverse[:2],
            (size, size),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_WRAP if ground.periodic else cv2.BORDER_REPLICATE,
        ).astype(np.float32)
        north = (np.arange(size, dtype=np.float32) + 0.5) * s - half  # per column
        east = half - (np.arange(size, dtype=np.float32) + 0.5) * s  # per row
        relief = self._relief(terrain, size)  # smooth relief for shading (no slope)
        gn, ge = terrain.gradient
        # gradient: columns run north, rows run south (east decreases down the rows)
        dh_dn = np.gradient(relief, s, axis=1) + np.float32(gn)
        dh_de = -np.gradient(relief, s, axis=0) + np.float32(ge)
        sun = self.sun.toward_ned.astype(np.float32)
        norm = np.sqrt(dh_dn * dh_dn + dh_de * dh_de + 1.0)
        cos_inc = np.clip((-dh_dn * sun[0] - dh_de * sun[1] - sun[2]) / norm, 0.0, None)
        rocks, tone = self._rocks(terrain, north, east, cos_inc)  # facets lit in cos_inc
        shadow = self._relief_shadow(terrain, size)
        self._rock_shadows(terrain, north, east, relief, rocks, shadow)
        light = (AMBIENT + DIFFUSE * cos_inc * (1.0 - shadow)) / self.sun.flat_light
        is_rock = rocks > _ROCK_MIN_M
        if is_rock.any():
            stone = albedo.reshape(-1, 3).mean(axis=0) * 0.9 + 8.0
            albedo[is_rock] = stone[None, :] * tone[is_rock][:, None]
        albedo *= self._crater_tone(terrain, north, east)[..., None]
        rgb = np.clip(np.rint(albedo * light[..., None]), 0, 255).astype(np.uint8)
        self.region = GroundMap(rgb=rgb, texel_to_ne=to_ne, periodic=False, name="site")
        self.rock_max_m = float(rocks.max()) if is_rock.any() else 0.0
        level = np.ones((size, size), np.uint8)
        if is_rock.any():
            level[is_rock] = 2 + np.rint(rocks[is_rock] / self.rock_max_m * 253.0).astype(np.uint8)
        self.rock_level = level

    @staticmethod
    def _relief(terrain: Terrain, size: int) -> np.ndarray:
        """The relief and craters (slope aside) at every texel, bicubic between the 1 m nodes
        (smooth shading; the geometry itself is bilinear)."""
        if terrain.heights is None:
            return np.zeros((size, size), np.float32)
        s, half = REGION_TEXEL_M, SITE_HALF_M
        col = (np.arange(size, dtype=np.float32) + 0.5) * s / GRID_M  # node index north
        row = (2 * half - (np.arange(size, dtype=np.float32) + 0.5) * s) / GRID_M  # east
        # heights[i, j]: i north, j east -> an image with x = j (east), y = i (north)
        map_x = np.broadcast_to(row[:, None], (size, size)).astype(np.float32)
        map_y = np.broadcast_to(col[None, :], (size, size)).astype(np.float32)
        return cv2.remap(
            terrain.heights.astype(np.float32),
            map_x,
            map_y,
            cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_REPLICATE,
        )

    def _rocks(self, terrain: Terrain, north, east, cos_inc) -> tuple[np.ndarray, np.ndarray]:
        """Each texel's rock height above the ground under it (the site's surface: the highest
        of the ground and each rock on its base) and the rock's albedo tone; the light on each
        rock texel's facet goes into ``cos_inc``."""
        s, half, size = REGION_TEXEL_M, SITE_HALF_M, len(north)
        rocks = np.zeros((size, size), np.float32)
        tone = np.ones((size, size), np.float32)
        stones = terrain.rocks
        rng = np.random.default_rng(len(stones))
        tones = rng.uniform(0.72, 1.08, len(stones)).astype(np.float32)
        toward = self.sun.toward_ned
        for k in range(len(stones)):
            rn, re, reach = stones.north[k], stones.east[k], stones.extent[k] + s
            c0, c1 = (int(np.clip((v + half) / s, 0, size)) for v in (rn - reach, rn + reach))
            r0, r1 = (int(np.clip((half - v) / s, 0, size)) for v in (re + reach, re - reach))
            if c1 <= c0 or r1 <= r0:
                continue
            nn, ee = np.meshgrid(north[c0:c1], east[r0:r1])
            z, facet = stones.local_height(k, nn - rn, ee - re)
            above = (stones.base[k] + z - terrain.base_heights(nn, ee)).astype(np.float32)
            window = rocks[r0:r1, c0:c1]
            mine = (z > 0.0) & (above > window)
            window[mine] = above[mine]
            # a facet's normal (x north, y east, z up) in NED is (x, y, -z)
            nrm = stones.normals[k][facet]
            lit = nrm[..., 0] * toward[0] + nrm[..., 1] * toward[1] - nrm[..., 2] * toward[2]
            cos_inc[r0:r1, c0:c1][mine] = np.clip(lit[mine], 0.0, None)
            shade = (tones[k] * (1.0 + 0.08 * (facet % 3 - 1))).astype(np.float32)
            tone[r0:r1, c0:c1][mine] = shade[mine]
        return rocks, tone

    def _relief_shadow(self, terrain: Terrain, size: int) -> np.ndarray:
        """The relief's cast shadow (0..1, soft between the 1 m nodes): a node is in shadow when
        the ground toward the sun rises above its ray."""
        sun = self.sun
        if terrain.heights is None or sun.elevation_deg >= 89.0:
            return np.zeros((size, size), np.float32)
        el, az = math.radians(sun.elevation_deg), math.radians(sun.azimuth_deg)
        nodes = np.arange(terrain.heights.shape[0]) * GRID_M - SITE_HALF_M
        nn, ee = np.meshgrid(nodes, nodes, indexing="ij")
        base = terrain.base_heights(nn, ee)
        rise = float(np.ptp(base))
        step = 0.5 * GRID_M
        steps = min(240, math.ceil(rise / (step * math.tan(el))) + 1)
        dn, de = math.cos(az) * step, math.sin(az) * step
        dark = np.zeros(base.shape, bool)
        for k in range(1, steps + 1):
            ahead = terrain.base_heights(nn + k * dn, ee + k * de)
            dark |= ahead > base + k * step * math.tan(el) + 1e-3
        # node (i north, j east) -> texel (row east, col north), bilinear
        col = (np.arange(size, dtype=np.float32) + 0.5) * REGION_TEXEL_M / GRID_M
        row = (
            2 * SITE_HALF_M - (np.arange(size, dtype=np.float32) + 0.5) * REGION_TEXEL_M
        ) / GRID_M
        map_x = np.broadcast_to(row[:, None], (size, size)).astype(np.float32)
        map_y = np.broadcast_to(col[None, :], (size, size)).astype(np.float32)
        return cv2.remap(
            dark.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )

    def _rock_shadows(self, terrain, north, east, relief, rocks, shadow) -> None:
        """Each rock's cast shadow: texels whose ray toward the sun meets it."""
        sun = self.sun
        stones = terrain.rocks
        if not len(stones) or sun.elevation_deg >= 89.0:
            return
        s, half, size = REGION_TEXEL_M, SITE_HALF_M, shadow.shape[0]
        el, az = math.radians(sun.elevation_deg), math.radians(sun.azimuth_deg)
        u = (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))
        gn, ge = terrain.gradient
        for k in range(len(stones)):
            rn, re, ext = stones.north[k], stones.east[k], stones.extent[k] + s
            # the window: the rock and its shadow side (away from the sun)
            reach = (stones.height[k] + ext * math.hypot(gn, ge)) / math.tan(el)
            nb = sorted((rn - ext, rn + ext, rn - reach * math.cos(az) - ext))
            eb = sorted((re - ext, re + ext, re - reach * math.sin(az) - ext))
            nb[-1] = max(nb[-1], rn - reach * math.cos(az) + ext)
            eb[-1] = max(eb[-1], re - reach * math.sin(az) + ext)
            c0, c1 = (int(np.clip((v + half) / s, 0, size)) for v in (nb[0], nb[-1]))
            r0, r1 = (int(np.clip((half - v) / s, 0, size)) for v in (eb[-1], eb[0]))
            if c1 <= c0 or r1 <= r0:
                continue
            nn, ee = np.meshgrid(north[c0:c1], east[r0:r1])
            z = gn * nn + ge * ee + relief[r0:r1, c0:c1] + rocks[r0:r1, c0:c1] - stones.base[k]
            hit = stones.shadowed(k, nn - rn, ee - re, z, u)
            shadow[r0:r1, c0:c1][hit] = 1.0

    @staticmethod
    def _crater_tone(terrain: Terrain, north, east) -> np.ndarray:
        """Albedo factor of the craters: bright ejecta around the rim, a darker floor."""
        s, half = REGION_TEXEL_M, SITE_HALF_M
        size = len(north)
        tone = np.ones((size, size), np.float32)
        for cn, ce, radius in terrain.craters:
            reach = 3.0 * radius
            c0, c1 = (int(np.clip((v + half) / s, 0, size)) for v in (cn - reach, cn + reach))
            r0, r1 = (int(np.clip((half - v) / s, 0, size)) for v in (ce + reach, ce - reach))
            d = np.hypot(north[None, c0:c1] - cn, east[r0:r1, None] - ce) / radius
            ring = 1.0 + 0.10 * np.exp(-(((d - 1.25) / 0.45) ** 2)) - 0.06 * (d < 0.8)
            tone[r0:r1, c0:c1] *= ring.astype(np.float32)
        return tone
