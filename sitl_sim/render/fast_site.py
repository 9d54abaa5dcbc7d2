"""The fast renderer's landing site: tilted and raised planes, relief, rock slices, the vehicle.

:class:`FastSite` draws one :class:`~sitl_sim.render.site_look.SiteLook` (see there for what the
textures hold) with the tools of :mod:`sitl_sim.render.render_fast`, under its frame budget:

- **ground** on the slope plane: one homography (the plane ``height = g . (n, e)``); with relief
  or craters, a per-pixel map instead: rays through a grid of pixels 8 apart meet the surface
  (the slope plane plus the bilinear heightfield, by fixed-point steps), the north/east they hit
  is interpolated bilinearly to every pixel, and every ground texture is ``cv2.remap``-ed through
  it (the ground beyond the region only when the view reaches past it);
- **rocks**: the region's texture again in up to :data:`ROCK_SLICES` slices at heights through
  the tallest rock, each slice the texels of rock at least that high, drawn bottom up on its
  plane (or the relief lifted by it): a stepped-pyramid model of each dome. As many slices as
  pixels of parallax the tallest rock shows at the image's edge from this height (none below
  half a pixel), so a slice is never more than half a pixel from the dome it stands for;
- **the vehicle**: its solids' faces that look at the camera, clipped to the ground plane and the
  camera's near plane, projected and filled, lit as
  :func:`~sitl_sim.render.site_look.face_light` says; the solids under the pad first (lowest
  first), then the pad's layers on its plane at the frame's time (a homography of the pad frame),
  then any solid standing above the pad.

A rock or a hill never hides the vehicle (the painter's order above); the vehicle casts no
shadow. Textures of two values per texel (level and grey, a picture pad's inside and grey) are
packed in one uint16 channel: OpenCV warps one channel several times faster than two.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sitl_sim.render.ground import LUMA_Q8
from sitl_sim.render.site_look import SiteLook
from sitl_sim.render.terrain import AMBIENT, DIFFUSE
from sitl_sim.site.terrain import GRID_M, SITE_HALF_M

__all__ = ["BODY_TO_IMAGE", "ROCK_SLICES", "FastSite"]

BODY_TO_IMAGE = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""Body FRD -> image axes (image right = body right, image down = body back, optical axis =
body down)."""
ROCK_SLICES = 3
_STEP_PX = 8  # the relief's ray grid: one ray every 8 pixels
_NEAR_M = 0.02  # pybullet's near plane
_SUB = 16  # fillConvexPoly's fixed point (4 bits)
_TILES = 4  # a periodic ground is warped from 4 x 4 tiles of it
_EDGE = 0.8  # tan of the largest angle off the optical axis the parallax is judged at


def _inset(pts: list, by: float = 0.5) -> list | None:
    """A convex polygon (list of (x, y) pixels) with every edge moved ``by`` inward: OpenCV
    fills the pixels within half a pixel of a polygon, TinyRenderer those whose centre is inside
    it. None when nothing is left. Plain floats: a face has a handful of corners."""
    m = len(pts)
    area2 = sum(pts[i][0] * pts[i - 1][1] - pts[i - 1][0] * pts[i][1] for i in range(m))
    if abs(area2) < 1e-9:
        return None
    sign = -1.0 if area2 > 0.0 else 1.0
    lines = []  # per edge: a point of its moved line, its direction, its inward normal
    for i in range(m):
        (x0, y0), (x1, y1) = pts[i], pts[(i + 1) % m]
        ex, ey = x1 - x0, y1 - y0
        length = math.hypot(ex, ey)
        if length < 1e-9:
            continue
        nx, ny = -ey / length * sign, ex / length * sign
        lines.append((x0 + by * nx, y0 + by * ny, ex, ey, nx, ny))
    if len(lines) < 3:
        return None
    out = []
    for i in range(len(lines)):  # vertex i: where the moved lines i - 1 and i meet
        bx, by_, ex, ey = lines[i][:4]
        px, py, pex, pey = lines[i - 1][:4]
        det = pex * ey - pey * ex
        if abs(det) < 1e-12:
            return None
        t = ((bx - px) * ey - (by_ - py) * ex) / det
        out.append((px + t * pex, py + t * pey))
    # every new corner inside every moved line: else the polygon was thinner than a pixel
    # somewhere and turned inside out
    for bx, by_, _, _, nx, ny in lines:
        for x, y in out:
            if (x - bx) * nx + (y - by_) * ny < -1e-6:
                return None
    return out


def _fill(image: np.ndarray, pix: list, grey: int) -> None:
    """Fill the pixels whose centre lies inside the convex polygon ``pix`` ((x, y) list)."""
    inner = _inset([(min(max(x, -1e4), 1e4), min(max(y, -1e4), 1e4)) for x, y in pix])
    if inner is not None:
        pts = np.rint(np.array(inner) * _SUB).astype(np.int32)
        cv2.fillConvexPoly(image, pts, grey, cv2.LINE_8, 4)


def _clip(poly: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The part of a convex polygon (m, d) where ``values`` (m,) >= 0 (Sutherland-Hodgman)."""
    out = []
    m = len(poly)
    for i in range(m):
        a, b = poly[i], poly[(i + 1) % m]
        fa, fb = values[i], values[(i + 1) % m]
        if fa >= 0.0:
            out.append(a)
        if (fa >= 0.0) != (fb >= 0.0):
            out.append(a + (b - a) * (fa / (fa - fb)))
    return np.array(out) if out else np.zeros((0, poly.shape[1]))


class _RayGrid:
    """Pixels every :data:`_STEP_PX` (and one beyond each edge) whose maps ``cv2.resize``
    interpolates to every pixel exactly bilinearly: node ``i`` sits at pixel ``(i - 1/2) step
    - 1/2``, and resizing the node grid ``step`` times then dropping ``step`` pixels each side
    puts it there."""

    def __init__(self, k: np.ndarray, size: tuple[int, int]) -> None:
        w, h = size
        self.size = size
        self.nodes = (w // _STEP_PX + 2, h // _STEP_PX + 2)
        self.exact = w % _STEP_PX == 0 and h % _STEP_PX == 0
        if self.exact:
            u = (np.arange(self.nodes[0]) - 0.5) * _STEP_PX - 0.5
            v = (np.arange(self.nodes[1]) - 0.5) * _STEP_PX - 0.5
        else:  # any other size: nodes over the image, interpolated by matrices
            u, v = np.linspace(0.0, w - 1.0, 17), np.linspace(0.0, h - 1.0, 17)
            self.wx, self.wy = _interp_matrix(w, 17), _interp_matrix(h, 17)
        uu, vv = np.meshgrid(u, v)
        self.rays = np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)])

    def upsample(self, maps: np.ndarray) -> np.ndarray:
        """(rows, cols, c) node values -> (h, w, c) float32 per pixel."""
        w, h = self.size
        if self.exact:
            big = cv2.resize(
                maps.astype(np.float32),
                (maps.shape[1] * _STEP_PX, maps.shape[0] * _STEP_PX),
                interpolation=cv2.INTER_LINEAR,
            )
            return big[_STEP_PX : _STEP_PX + h, _STEP_PX : _STEP_PX + w]
        return np.einsum("pi,ijc,qj->pqc", self.wy, maps, self.wx).astype(np.float32)


def _interp_matrix(pixels: int, nodes: int) -> np.ndarray:
    """(pixels, nodes) linear interpolation weights from nodes spread over 0..pixels-1."""
    pos = np.arange(pixels) * (nodes - 1) / (pixels - 1)
    i0 = np.minimum(pos.astype(int), nodes - 2)
    frac = pos - i0
    w = np.zeros((pixels, nodes))
    w[np.arange(pixels), i0] = 1.0 - frac
    w[np.arange(pixels), i0 + 1] = frac
    return w


class _Vehicle:
    """Solids' faces as arrays (pad frame): shared vertices, per face its vertex indices (padded
    to the longest face by repeating its first), normal, colour and ``normal . first vertex``,
    in drawing order. Dot products are the same in the pad frame as in NED, so which faces look
    at the camera and how the sun lights them need no per-vertex work. A face inside another
    solid (a wheel's top under the bed) or under its own (a bottom) is never seen: left out."""

    def __init__(self, solids) -> None:
        vertices, faces, normals, rgb = [], [], [], []
        self.solid_of: list[int] = []  # each face's solid (its index in ``solids``)
        for number, solid in enumerate(solids):
            base = sum(len(v) for v in vertices)
            ring = len(solid.outline)
            sides = solid.faces()
            vertices += [sides[0][0], sides[1][0]]  # the top ring, the bottom ring
            rings = [base + np.arange(ring), None]
            rings += [
                base + np.array([i, ring + i, ring + (i + 1) % ring, (i + 1) % ring])
                for i in range(ring)
            ]
            others = [o.planes() for o in solids if o is not solid]
            for (verts, normal, is_top), idx in zip(sides, rings, strict=True):
                if idx is None or any(np.all(verts @ n.T < d - 1e-9) for n, d in others):
                    continue
                faces.append(idx)
                self.solid_of.append(number)
                normals.append(normal)
                rgb.append(solid.top_rgb if is_top else solid.rgb)
        self.count = len(faces)
        if not faces:
            return
        self.vertices = np.vstack(vertices)
        width = max(len(f) for f in faces)
        self.faces = [f.tolist() for f in faces]
        self.padded = np.array([np.concatenate([f, np.full(width - len(f), f[0])]) for f in faces])
        self.normals = np.array(normals)
        self.offsets = np.einsum("ij,ij->i", self.normals, self.vertices[self.padded[:, 0]])
        self.rgb = np.array(rgb)
        self.following = np.roll(self.padded, -1, axis=1)  # each corner's next one
        self._luma = np.array(LUMA_Q8)
        self.split = self.count  # the first face above the pad (set by the caller)
        # faces under a solid's top and within its outline: hidden from a camera above it
        self.roofs = []
        for number, solid in enumerate(solids):
            planes, offsets = solid.planes()
            planes, offsets = planes[:-2, :2], offsets[:-2]  # the outline's edges
            under = np.array(
                [
                    bool(
                        self.solid_of[f] != number
                        and np.all(self.vertices[idx, :2] @ planes.T <= offsets + 1e-6)
                        and np.all(self.vertices[idx, 2] >= solid.z_top - 1e-9)
                    )
                    for f, idx in enumerate(self.faces)
                ]
            )
            if under.any():
                self.roofs.append((planes, offsets, solid.z_top, under))

    def draw(self, image, k, to_cam, cam, p, r, gradient, sun, between) -> None:
        """Fill the faces that look at the camera, the solids under the pad first, then
        ``between()`` (the pad), then the solids above it."""
        if not self.count:
            between()
            return
        local_cam = r.T @ (cam - p)
        facing = self.normals @ local_cam > self.offsets
        for planes, offsets, top, under in self.roofs:
            if local_cam[2] < top and np.all(planes @ local_cam[:2] <= offsets):
                facing &= ~under  # the camera looks down on this solid's top: all under it hidden
        if not facing.any():
            between()
            return
        gn, ge = gradient
        rel = self.vertices @ (to_cam @ r).T + to_cam @ (p - cam)
        above = -(self.vertices @ (r.T @ np.array([gn, ge, 1.0]))) - (gn * p[0] + ge * p[1] + p[2])
        ok = ((above >= 0.0) & (rel[:, 2] >= _NEAR_M))[self.padded].all(axis=1)
        light = (AMBIENT + DIFFUSE * np.clip(self.normals @ (r.T @ sun[0]), 0.0, None)) / sun[1]
        # the colour as pybullet's TinyRenderer takes it: a float per channel truncated to a
        # byte, then the camera's luma
        rgb = (np.minimum(self.rgb * light[:, None], 1.0) * 255.0).astype(np.int64)
        greys = ((rgb @ self._luma + 128) >> 8).tolist()
        pix = rel @ k.T
        pix = pix[:, :2] / np.maximum(pix[:, 2:3], _NEAR_M)
        # faces of under half a pixel cover no pixel centre (or one): not worth their cost
        x, y = pix[:, 0], pix[:, 1]
        cross = x[self.padded] * y[self.following] - x[self.following] * y[self.padded]
        facing &= (np.abs(cross.sum(axis=1)) >= 1.0) | ~ok
        pix = pix.tolist()
        pending = True  # the pad still to draw
        for f in np.flatnonzero(facing).tolist():
            if pending and f >= self.split:
                between()
                pending = False
            idx = self.faces[f]
            if ok[f]:
                _fill(image, [pix[i] for i in idx], greys[f])
                continue
            # partly under the ground (the water) or behind the near plane: cut there
            poly = _clip(rel[idx], above[idx])
            if len(poly) >= 3:
                poly = _clip(poly, poly[:, 2] - _NEAR_M)
            if len(poly) < 3:
                continue
            _fill(image, ((poly @ k.T)[:, :2] / poly[:, 2:3]).tolist(), greys[f])
        if pending:
            between()


class FastSite:
    """Draws a site's ground, rocks, vehicle and moving pad (see the module docstring).

    ``layers``: the pad's layers as the fast renderer holds them, ``(texels, texel -> pad
    (x, y) map, top height, grey lookup | None)``.
    """

    def __init__(self, look: SiteLook, layers: list) -> None:
        self.look = look
        site = look.site
        self._layers = layers
        self._base = look.base
        self._base_mono = look.base.mono
        self._base_border = cv2.BORDER_WRAP if look.base.periodic else cv2.BORDER_CONSTANT
        self._tiles = None
        if look.base.periodic and look.base.tile_m > 0.0:
            # a square tile: TILES x TILES of it and a shift by whole tiles replace BORDER_WRAP
            # (several times slower) while the view's ground fits in TILES - 1 tiles
            self._tiles = np.tile(look.base.mono, (_TILES, _TILES))
        terrain = site.terrain
        self._gradient = terrain.gradient if terrain is not None else (0.0, 0.0)
        self._heights = None
        if look.heightfield:
            self._heights = terrain.heights.astype(np.float32)
        self._region = None
        if look.region is not None:
            self._region = (look.rock_level.astype(np.uint16) << 8) | look.region.mono
        self._rock_max = look.rock_max_m
        self._grid: _RayGrid | None = None
        self._still = None if site.moves else site.motion.frame(0.0)
        lower = sorted((s for s in site.vehicle if s.z_top >= 0.0), key=lambda s: -s.z_top)
        upper = sorted((s for s in site.vehicle if s.z_top < 0.0), key=lambda s: -s.z_top)
        self._vehicle = _Vehicle([*lower, *upper])
        self._vehicle.split = sum(1 for i in self._vehicle.solid_of if i < len(lower))
        self._sun = (look.sun.toward_ned, look.sun.flat_light)

    # ------------------------------------------------------------------ the frame

    def render(self, k: np.ndarray, pos_ned_m, rot: np.ndarray, size, time_s: float):
        cam = np.array([float(v) for v in pos_ned_m])
        to_cam = BODY_TO_IMAGE @ rot.T  # an NED offset from the camera -> camera axes
        proj = k @ to_cam  # -> homogeneous pixel
        if self._heights is None:
            image = self._planes(proj, cam, size, float(k[0, 0]))
        else:
            image = self._relief(k, to_cam, cam, size)
        p, r = self._still if self._still is not None else self.look.site.motion.frame(time_s)
        self._vehicle.draw(
            image,
            k,
            to_cam,
            cam,
            p,
            r,
            self._gradient,
            self._sun,
            lambda: self._pad(image, proj, cam, p, r, size),
        )
        return image

    def _slices(self, cam: np.ndarray, focal_px: float) -> list[tuple[float, int]]:
        """(height, least level) of each rock slice worth drawing from ``cam``: as many as
        pixels of parallax the tallest rock shows at the image's edge (up to ROCK_SLICES)."""
        if self._region is None or self._rock_max <= 0.0:
            return []
        gn, ge = self._gradient
        above = max(-cam[2] - (gn * cam[0] + ge * cam[1]) - self._rock_max, 0.1)
        parallax_px = focal_px * _EDGE * self._rock_max / above
        count = min(ROCK_SLICES, math.ceil(parallax_px - 0.5))
        return [
            ((i + 0.5) / count * self._rock_max, 2 + math.ceil(253.0 * i / count))
            for i in range(count)
        ]

    @staticmethod
    def _paint(image: np.ndarray, layer: np.ndarray, least: int) -> None:
        """Paint the grey (low byte) of the texels whose level (high byte) is >= ``least``."""
        np.copyto(image, layer.astype(np.uint8), where=layer >= (least << 8))

    def _planes(self, proj: np.ndarray, cam: np.ndarray, size, focal_px: float) -> np.ndarray:
        """Ground, region and rock slices as planes parallel to the slope (homographies)."""
        gn, ge = self._gradient

        def plane(lift: float) -> np.ndarray:
            return proj @ np.array(
                [[1.0, 0.0, -cam[0]], [0.0, 1.0, -cam[1]], [-gn, -ge, -lift - cam[2]]]
            )

        ground = plane(0.0)
        image = self._base_warp(ground, cam, size)
        if self._region is None:
            return image
        to_ne = self.look.region.texel_to_ne
        for lift, least in [(0.0, 1), *self._slices(cam, focal_px)]:
            h = ground if lift == 0.0 else plane(lift)
            layer = cv2.warpPerspective(
                self._region, h @ to_ne, size, flags=cv2.INTER_NEAREST, borderValue=0
            )
            self._paint(image, layer, least)
        return image

    def _base_warp(self, ground: np.ndarray, cam: np.ndarray, size) -> np.ndarray:
        """The ground beyond the region through the homography ``ground`` (plane -> pixel)."""
        to_ne = self._base.texel_to_ne
        h = ground @ to_ne
        w, hgt = size
        pixel_corners = np.array([[0, w, w, 0], [0, 0, hgt, hgt], [1, 1, 1, 1.0]])
        try:
            # the texels under the image's corners (none: the camera lies in the ground's plane,
            # a vehicle come down on the ground)
            corners = np.linalg.solve(h, pixel_corners) if self._tiles is not None else None
        except np.linalg.LinAlgError:
            corners = None
        if self._tiles is not None and corners is not None:
            # moved by whole tiles to the tiling's corner
            rows, cols = self._base_mono.shape
            if np.all(corners[2] * np.sign(corners[2, 0]) > 1e-9):  # all on the ground
                col, row = corners[0] / corners[2], corners[1] / corners[2]
                dc = -cols * math.floor((col.min() - 1.0) / cols)
                dr = -rows * math.floor((row.min() - 1.0) / rows)
                if col.max() + dc + 1.0 < _TILES * cols and row.max() + dr + 1.0 < _TILES * rows:
                    shift = np.array([[1.0, 0.0, -dc], [0.0, 1.0, -dr], [0.0, 0.0, 1.0]])
                    return cv2.warpPerspective(
                        self._tiles, h @ shift, size, flags=cv2.INTER_NEAREST, borderValue=0
                    )
        return cv2.warpPerspective(
            self._base_mono,
            h,
            size,
            flags=cv2.INTER_NEAREST,
            borderMode=self._base_border,
            borderValue=0,
        )

    def _surface(self, k, to_cam, cam, size) -> tuple[np.ndarray, bool]:
        """Per pixel (h, w, 4): north and east where its ray meets the ground (slope + relief),
        and how far they move per metre the surface is lifted; and whether every ray meets it
        within the region."""
        if self._grid is None or self._grid.size != tuple(size):
            self._grid = _RayGrid(k, tuple(size))
        grid = self._grid
        d = np.einsum("ij,jkl->ikl", to_cam.T, grid.rays)  # NED directions
        gn, ge = self._gradient
        denom = d[2] + gn * d[0] + ge * d[1]
        sky = denom <= 1e-6  # rays that never meet the ground: far away, out of every texture
        inv = np.where(sky, 0.0, 1.0 / np.where(sky, 1.0, denom))
        dn, de = d[0] * inv, d[1] * inv  # north, east per metre of (plane height - lift)
        base = np.float32(-(cam[2] + gn * cam[0] + ge * cam[1]))
        # the heightfield's node coordinates (i north = row, j east = col) of a ray's point
        c0 = np.float32((cam[1] + SITE_HALF_M) / GRID_M)
        r0 = np.float32((cam[0] + SITE_HALF_M) / GRID_M)
        dc, dr = (de / GRID_M).astype(np.float32), (dn / GRID_M).astype(np.float32)
        lift = np.zeros(denom.shape, np.float32)
        for _ in range(3):  # fixed-point steps: the point under the lifted plane, lifted there
            t = base - lift
            lift = cv2.remap(
                self._heights, c0 + t * dc, r0 + t * dr, cv2.INTER_LINEAR, borderValue=0.0
            )
        t = base - lift
        maps = np.stack([cam[0] + t * dn, cam[1] + t * de, -dn, -de], axis=-1)
        maps[sky, :2] = 1e7
        inside = bool(np.abs(maps[..., :2]).max() < SITE_HALF_M)
        return grid.upsample(maps), inside

    @staticmethod
    def _texel_maps(to_ne: np.ndarray, n, e, shift: bool = True) -> tuple[np.ndarray, ...]:
        """Texel (col, row) of north/east maps (``shift`` False: of a displacement)."""
        inv = np.linalg.inv(to_ne)
        c0, r0 = (inv[0, 2], inv[1, 2]) if shift else (0.0, 0.0)
        return (
            cv2.addWeighted(n, inv[0, 0], e, inv[0, 1], c0),
            cv2.addWeighted(n, inv[1, 0], e, inv[1, 1], r0),
        )

    def _relief(self, k, to_cam, cam, size) -> np.ndarray:
        """Ground, region and rock slices on the relief (per-pixel maps)."""
        maps, inside = self._surface(k, to_cam, cam, size)
        n, e, dn, de = (np.ascontiguousarray(maps[..., i]) for i in range(4))
        if inside:  # the region covers the whole view
            image = np.zeros((size[1], size[0]), np.uint8)
        else:
            col, row = self._texel_maps(self._base.texel_to_ne, n, e)
            image = cv2.remap(
                self._base_mono, col, row, cv2.INTER_NEAREST, borderMode=self._base_border
            )
        col, row = self._texel_maps(self.look.region.texel_to_ne, n, e)
        slices = self._slices(cam, float(k[0, 0]))
        if slices:
            dcol, drow = self._texel_maps(self.look.region.texel_to_ne, dn, de, shift=False)
        for lift, least in [(0.0, 1), *slices]:
            mc, mr = col, row
            if lift:
                mc, mr = cv2.scaleAdd(dcol, lift, col), cv2.scaleAdd(drow, lift, row)
            layer = cv2.remap(self._region, mc, mr, cv2.INTER_NEAREST, borderValue=0)
            self._paint(image, layer, least)
        return image

    # ------------------------------------------------------------------ the pad

    def _pad(self, image, proj, cam, p, r, size) -> None:
        down = r[:, 2]
        for texels, to_ne, top, grey in self._layers:
            origin = p - top * down
            if float((cam - origin) @ -down) <= 0.0:
                continue  # the camera is not above this layer
            h = proj @ np.column_stack([r[:, 0], r[:, 1], origin - cam]) @ to_ne
            layer = cv2.warpPerspective(
                texels, h, size, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT
            )
            if grey is None:  # a picture: inside << 8 | grey
                np.copyto(image, layer.astype(np.uint8), where=layer >= 0x100)
            else:  # labels: 0 = none, else the grey of grey[label] (a LUT)
                np.copyto(image, cv2.LUT(layer, grey), where=layer != 0)
