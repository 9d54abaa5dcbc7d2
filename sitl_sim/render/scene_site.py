"""The reference scene's landing site: meshes for the sloped ground, the relief, rocks, the vehicle
and the pad on it, in one pybullet client (its id passed on every call).

Built from a :class:`~sitl_sim.render.site_look.SiteLook`, the textures the fast renderer draws
too, so the two can be held to the same image:

- the ground beyond the region: quads of :data:`QUAD_M` on the slope plane, textured with
  :attr:`SiteLook.base` (each quad's uvs shifted by whole tiles, as pybullet wraps them); with no
  slope and no region, the scene's own nominal ground;
- the region: the heightfield's 1 m cells as two triangles each (or the slope plane in quads),
  textured with :attr:`SiteLook.region`;
- each rock: rings of vertices on its facets out to its foot (on the ground under it), textured
  with the region (its top view's colours);
- the vehicle: one mesh per face, lit per frame as :func:`~sitl_sim.render.site_look.face_light`
  says (the renderer's own light is fixed overhead; every mesh's normal points up so that it
  adds nothing);
- the pad's boxes (or picture quad) in the pad frame, moved with it.

Every surface but the vehicle is single-sided, facing up (the camera is always above it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from sitl_sim.errors import SimError
from sitl_sim.render.ground import GroundMap, PadLook, PadTexture
from sitl_sim.render.site_look import SiteLook, face_light
from sitl_sim.site.terrain import GRID_M, SITE_HALF_M

__all__ = ["QUAD_M", "SiteBodies"]

QUAD_M = 10.0
_N = np.diag([1.0, -1.0, -1.0])  # NED <-> pybullet's NWU (its own inverse)
_RIM = (0.0, 0.25, 0.5, 0.7, 0.85, 0.95, 1.0)  # a rock's rings, as fractions of its foot
_SEGMENTS = 16


def _quat_xyzw(m: np.ndarray) -> list[float]:
    """pybullet's quaternion (x, y, z, w) of a rotation matrix."""
    t = m[0, 0] + m[1, 1] + m[2, 2]
    if t > 0.0:
        s = 2.0 * math.sqrt(t + 1.0)
        w, x = 0.25 * s, (m[2, 1] - m[1, 2]) / s
        y, z = (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        w, x = (m[2, 1] - m[1, 2]) / s, 0.25 * s
        y, z = (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        w, x = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s
        y, z = 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        w, x = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s
        y, z = (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return [float(x), float(y), float(z), float(w)]


def _up_facing(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles (k, 3) wound counterclockwise seen from above (+z in the scene): the side
    TinyRenderer draws."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    z = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    out = triangles.copy()
    flip = z < 0.0
    out[flip] = triangles[flip][:, [0, 2, 1]]
    return out


def _uv(to_ne: np.ndarray, shape, n, e) -> tuple[np.ndarray, np.ndarray]:
    """A texture's (u, v) at north/east: texel centre k <-> (k + .5) / size; TinyRenderer reads
    a mesh's v bottom-up."""
    inv = np.linalg.inv(to_ne)
    col = inv[0, 0] * n + inv[0, 1] * e + inv[0, 2]
    row = inv[1, 0] * n + inv[1, 1] * e + inv[1, 2]
    rows, cols = shape[:2]
    return (col + 0.5) / cols, 1.0 - (row + 0.5) / rows


class SiteBodies:
    """A site's bodies in pybullet client ``client`` (see the module docstring); ``place(t)``
    moves the pad and its vehicle to sim time ``t``."""

    def __init__(
        self,
        pb: Any,
        client: int,
        look: SiteLook,
        pad: PadLook,
        nominal_ground: Callable[[], None],
    ) -> None:
        self._pb, self._c, self.look = pb, client, look
        site = look.site
        terrain = site.terrain
        self._gradient = terrain.gradient if terrain is not None else (0.0, 0.0)
        if look.region is None and terrain is None:
            nominal_ground()  # flat ground (or water) as the scene always drew it
        else:
            self._plane_ground()
        if look.region is not None:
            self._region()
            if terrain is not None and len(terrain.rocks):
                self._rocks()
        self._faces: list[tuple[int, np.ndarray, tuple[float, float, float]]] = []
        for solid in site.vehicle:
            for verts, normal, is_top in solid.faces():
                body = self._mesh(
                    verts @ _N,
                    np.array([[0, i, i + 1] for i in range(1, len(verts) - 1)]),
                    double=True,
                )
                self._faces.append((body, normal, solid.top_rgb if is_top else solid.rgb))
        self._pad = self._pad_bodies(pad)
        self._moves = site.moves
        self._placed = False
        self.place(0.0)

    # ------------------------------------------------------------------ building

    def _mesh(
        self, vertices, triangles, uvs=None, texture: GroundMap | None = None, double=False
    ) -> int:
        pb, c = self._pb, self._c
        tris = np.asarray(triangles, dtype=int)
        if double:
            tris = np.vstack([tris, tris[:, [0, 2, 1]]])
        else:
            tris = _up_facing(np.asarray(vertices), tris)
        kwargs: dict[str, Any] = {}
        if uvs is not None:
            kwargs["uvs"] = np.asarray(uvs).tolist()
        shape = pb.createVisualShape(
            pb.GEOM_MESH,
            vertices=np.asarray(vertices).tolist(),
            indices=tris.ravel().tolist(),
            normals=[[0.0, 0.0, 1.0]] * len(vertices),
            physicsClientId=c,
            **kwargs,
        )
        if shape < 0:
            raise SimError("pybullet: could not create a site mesh")
        body = pb.createMultiBody(baseMass=0.0, baseVisualShapeIndex=shape, physicsClientId=c)
        if texture is not None:
            tex = pb.loadTexture(str(texture.png()), physicsClientId=c)
            if tex < 0:
                raise SimError("pybullet: could not load a site texture")
            pb.changeVisualShape(body, -1, textureUniqueId=tex, physicsClientId=c)
        return body

    def _height(self, n, e):
        gn, ge = self._gradient
        return gn * n + ge * e

    def _plane_ground(self) -> None:
        """QUAD_M quads on the slope plane over the whole ground, but the region."""
        base = self.look.base
        half = 300.0
        n0, e0 = np.meshgrid(np.arange(-half, half, QUAD_M), np.arange(-half, half, QUAD_M))
        n0, e0 = n0.ravel(), e0.ravel()
        if self.look.region is not None:
            inside = (n0 >= -SITE_HALF_M) & (n0 + QUAD_M <= SITE_HALF_M)
            inside &= (e0 >= -SITE_HALF_M) & (e0 + QUAD_M <= SITE_HALF_M)
            n0, e0 = n0[~inside], e0[~inside]
        ns = np.stack([n0, n0 + QUAD_M, n0 + QUAD_M, n0], axis=1)  # (quads, 4 corners)
        es = np.stack([e0, e0, e0 + QUAD_M, e0 + QUAD_M], axis=1)
        u, v = _uv(base.texel_to_ne, base.rgb.shape, ns, es)
        if base.periodic:  # whole tiles off, near [0, 1): TinyRenderer wraps uvs
            u = u - np.floor(u.mean(axis=1, keepdims=True))
            v = v - np.floor(v.mean(axis=1, keepdims=True))
        vertices = np.column_stack([ns.ravel(), -es.ravel(), self._height(ns, es).ravel()])
        k = 4 * np.arange(len(n0))[:, None]
        tris = np.concatenate([k + np.array([0, 1, 2]), k + np.array([0, 2, 3])])
        self._mesh(vertices, tris, np.column_stack([u.ravel(), v.ravel()]), base)

    def _region(self) -> None:
        """The region: the heightfield's cells (or the slope plane in quads)."""
        look = self.look
        terrain = look.site.terrain
        if look.heightfield:
            nodes = np.arange(terrain.heights.shape[0]) * GRID_M - SITE_HALF_M
            lift = terrain.heights
        else:
            nodes = np.arange(-SITE_HALF_M, SITE_HALF_M + 0.5 * QUAD_M, QUAD_M)
            lift = np.zeros((len(nodes), len(nodes)))
        nn, ee = np.meshgrid(nodes, nodes, indexing="ij")  # (i north, j east)
        z = self._height(nn, ee) + lift
        u, v = _uv(look.region.texel_to_ne, look.region.rgb.shape, nn, ee)
        m = len(nodes)
        vertices = np.column_stack([nn.ravel(), -ee.ravel(), z.ravel()])
        idx = np.arange(m * m).reshape(m, m)
        a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
        c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        tris = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
        self._mesh(vertices, tris, np.column_stack([u.ravel(), v.ravel()]), look.region)

    def _rocks(self) -> None:
        """Every rock as rings of vertices on its facets, its rim on the ground; one mesh."""
        terrain = self.look.site.terrain
        stones = terrain.rocks
        region = self.look.region
        angles = np.arange(_SEGMENTS) * 2 * math.pi / _SEGMENTS
        vertices, tris = [], []
        for k in range(len(stones)):
            rn, re, base = stones.north[k], stones.east[k], stones.base[k]
            rim = stones.rim(k, angles)
            first = len(vertices)
            xs = np.concatenate([[0.0], *(f * rim * np.cos(angles) for f in _RIM[1:])])
            ys = np.concatenate([[0.0], *(f * rim * np.sin(angles) for f in _RIM[1:])])
            ns, es = rn + xs, re + ys
            ground = terrain.base_heights(ns, es)
            z = np.maximum(ground, base + stones.local_height(k, xs, ys)[0])
            z[-_SEGMENTS:] = ground[-_SEGMENTS:]  # the rim on the ground
            vertices += np.column_stack([ns, -es, z]).tolist()
            for j in range(_SEGMENTS):
                j1 = (j + 1) % _SEGMENTS
                tris.append([first, first + 1 + j, first + 1 + j1])
                for ring in range(len(_RIM) - 2):
                    r0 = first + 1 + ring * _SEGMENTS
                    r1 = r0 + _SEGMENTS
                    tris += [[r0 + j, r1 + j, r1 + j1], [r0 + j, r1 + j1, r0 + j1]]
        vertices = np.array(vertices)
        u, v = _uv(region.texel_to_ne, region.rgb.shape, vertices[:, 0], -vertices[:, 1])
        self._mesh(vertices, np.array(tris), np.column_stack([u, v]), region)

    def _pad_bodies(self, pad: PadLook) -> list[int]:
        """The pad in its own frame (x forward, y left, z up in pybullet's axes)."""
        pb, c = self._pb, self._c
        if isinstance(pad, PadTexture):
            w, h = pad.size_m
            corners = ((h / 2, -w / 2), (h / 2, w / 2), (-h / 2, w / 2), (-h / 2, -w / 2))
            vertices = [[n, -e, pad.top_m] for n, e in corners]
            uvs = [[(e + w / 2) / w, (n + h / 2) / h] for n, e in corners]
            body = self._mesh(np.array(vertices), np.array([[0, 1, 2], [0, 2, 3]]), uvs)
            tex = pb.loadTexture(str(pad.png()), physicsClientId=c)
            if tex < 0:
                raise SimError("pybullet: could not load the pad texture")
            pb.changeVisualShape(body, -1, textureUniqueId=tex, physicsClientId=c)
            return [body]
        s = pad.side_m / 2
        a, w = pad.cross_length_m / 2, pad.cross_width_m / 2
        boxes = (
            ([s, s, 0.01], pad.green_rgb, pad.square_top_m),
            ([a, w, 0.01], pad.red_rgb, pad.cross_top_m),
            ([w, a, 0.01], pad.red_rgb, pad.cross_top_m),
        )
        bodies = []
        for half, rgb, top in boxes:
            shape = pb.createVisualShape(
                pb.GEOM_BOX,
                halfExtents=half,
                rgbaColor=[*rgb, 1],
                visualFramePosition=[0.0, 0.0, top - half[2]],
                physicsClientId=c,
            )
            bodies.append(
                pb.createMultiBody(baseMass=0.0, baseVisualShapeIndex=shape, physicsClientId=c)
            )
        return bodies

    # ------------------------------------------------------------------ each frame

    def place(self, time_s: float) -> None:
        """The pad and the vehicle where they are at ``time_s``, the vehicle lit for it."""
        if self._placed and not self._moves:
            return
        pb, c = self._pb, self._c
        p, r = self.look.site.motion.frame(time_s)
        position = (_N @ p).tolist()
        orientation = _quat_xyzw(_N @ r @ _N)
        for body in self._pad:
            pb.resetBasePositionAndOrientation(body, position, orientation, physicsClientId=c)
        for body, normal, rgb in self._faces:
            pb.resetBasePositionAndOrientation(body, position, orientation, physicsClientId=c)
            light = face_light(r @ normal, self.look.sun)
            colour = [min(1.0, ch * light) for ch in rgb]
            pb.changeVisualShape(body, -1, rgbaColor=[*colour, 1.0], physicsClientId=c)
        self._placed = True
