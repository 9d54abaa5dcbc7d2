"""The pybullet scene and the downward camera — the only code that knows pybullet's z-up world.

World: pybullet's frame here is NWU (x north, y west, z up), so a NED point ``(n, e, d)`` is
``(n, -e, -d)`` in pybullet (:func:`ned_to_scene`). The landing pad of the paper (a red cross on a
green square) lies at the origin on a large textured ground.

Camera: mounted at the vehicle's centre, looking along body +z (down), image up = body forward,
image right = body right, square image with the configured full field of view, rendered by
pybullet's TinyRenderer (software, no display) with an explicit physics client id on every call.
The colour render is converted to mono8 with the ITU-R BT.601 luma weights.
"""

from __future__ import annotations

import ctypes
import itertools
import math
import os
import sys
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np

from sitl_sim.config import CameraConfig
from sitl_sim.errors import SimError
from sitl_sim.physics.dynamics import quat_to_rotation
from sitl_sim.render.ground import (
    GROUND_HALF_SIDE_M,
    GroundMap,
    PadGeometry,
    PadLook,
    PadTexture,
    luma,
    nominal_ground,
)
from sitl_sim.render.scene_site import SiteBodies
from sitl_sim.render.site_look import SiteLook

if TYPE_CHECKING:
    from sitl_sim.render.terrain import Sun
    from sitl_sim.render.visual import CameraEffects
    from sitl_sim.site.site import Site

__all__ = ["Camera", "PadGeometry", "Renderer", "Scene", "make_renderer", "ned_to_scene"]


def _import_pybullet() -> Any:
    """``pybullet``, without the "pybullet build time: ..." line its C module ``printf``s at
    import (into every command's output, a JSON document on stdout included): file descriptors
    1 and 2 point at /dev/null while it loads, and C's stdio buffer is flushed there before
    they are given back (a pipe's buffer would otherwise reach the real stdout at exit)."""
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        import pybullet

        ctypes.CDLL(None).fflush(None)
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)
    return pybullet


pb = _import_pybullet()

_NED_TO_SCENE = np.diag([1.0, -1.0, -1.0])


def ned_to_scene(v_ned) -> np.ndarray:
    """A NED vector or point in pybullet's NWU world."""
    return _NED_TO_SCENE @ np.asarray(v_ned, dtype=float)


def _add_quad(mesh: tuple[list, list, list], corners_ne, corner_uvs) -> None:
    """Appends one ground quad (z = 0) to ``mesh`` (vertices, uvs, indices): its four corners
    (north, east) in order with their uvs, both faces drawn."""
    vertices, uvs, indices = mesh
    base = len(vertices)
    for (n, e), (u, v) in zip(corners_ne, corner_uvs, strict=True):
        vertices.append(ned_to_scene((n, e, 0.0)).tolist())
        uvs.append([u, v])
    indices += [base, base + 1, base + 2, base, base + 2, base + 3]
    indices += [base, base + 2, base + 1, base, base + 3, base + 2]  # both faces


class Renderer(Protocol):
    """What the camera renders from: :class:`Scene` (pybullet, the reference) or
    :class:`sitl_sim.render.render_fast.FastRenderer`; both draw the same ground map and pad."""

    def configure(
        self, ground: GroundMap, pad: PadLook, site: Site | None = None, sun: Sun | None = None
    ) -> None: ...

    def render(
        self, pos_ned_m, quat_wxyz, cfg: CameraConfig, time_s: float = 0.0
    ) -> np.ndarray: ...

    def close(self) -> None: ...


RENDERERS = ("pybullet", "fast")


def make_renderer(name: str) -> Renderer:
    """The renderer called ``name`` (``[camera] renderer`` of the sim config), on the nominal
    ground and pad."""
    if name == "pybullet":
        return Scene()
    if name == "fast":
        from sitl_sim.render.render_fast import FastRenderer

        return FastRenderer()
    raise SimError(f"renderer {name!r}; expected one of {list(RENDERERS)}")


class Scene:
    """A pybullet DIRECT client holding the ground and the pad. Close it (or use ``with``).

    The nominal ground is a 600 m box textured with :func:`~sitl_sim.render.ground.nominal_ground`
    (pybullet's own box UVs); a periodic ground map (:mod:`sitl_sim.render.terrain`) is a mesh of
    quads cut at the tile edges, each with uvs spanning its part of the tile, so texel (col, row)
    lies exactly where the map's ``texel_to_ne`` says. A landing site (:mod:`sitl_sim.site`) adds
    its slope, relief, rocks, vehicle and moving pad (:mod:`sitl_sim.render.scene_site`).
    """

    GROUND_HALF_SIDE_M = GROUND_HALF_SIDE_M
    QUAD_M = 10.0

    def __init__(self, pad: PadLook | None = None, ground: GroundMap | None = None) -> None:
        self._client = pb.connect(pb.DIRECT)
        if self._client < 0:
            raise SimError("pybullet: could not open a DIRECT client")
        self.ground: GroundMap | None = None
        self.pad: PadLook | None = None
        self._site: SiteBodies | None = None
        self._site_key: tuple | None = None
        try:
            self.configure(ground or nominal_ground(), pad or PadGeometry())
        except Exception:
            pb.disconnect(physicsClientId=self._client)
            raise

    @property
    def client_id(self) -> int:
        return self._client

    def configure(
        self, ground: GroundMap, pad: PadLook, site: Site | None = None, sun: Sun | None = None
    ) -> None:
        """Show ``ground`` and ``pad`` from now on (rebuilds the bodies if they changed), on
        ``site`` (None: the pad still on flat ground) lit by ``sun`` (None: overhead)."""
        key = None
        if site is not None:
            key = (id(site), None if sun is None else (sun.elevation_deg, sun.azimuth_deg))
        if ground is self.ground and pad == self.pad and key == self._site_key:
            return
        pb.resetSimulation(physicsClientId=self._client)
        self.ground = ground
        self.pad = pad
        self._site_key = key
        self._site = None
        if site is None:
            self._build()
            return
        look = SiteLook(ground, site, sun)
        self._site = SiteBodies(pb, self._client, look, pad, self._build_ground)

    def _box(self, half_extents, rgba, z_top: float) -> int:
        c = self._client
        shape = pb.createVisualShape(
            pb.GEOM_BOX, halfExtents=half_extents, rgbaColor=rgba, physicsClientId=c
        )
        return pb.createMultiBody(
            baseMass=0.0,
            baseVisualShapeIndex=shape,
            basePosition=[0.0, 0.0, z_top - half_extents[2]],
            physicsClientId=c,
        )

    def _build(self) -> None:
        self._build_ground()
        self._build_pad()

    def _build_ground(self) -> None:
        c = self._client
        h = self.GROUND_HALF_SIDE_M
        if self.ground.periodic and self.ground.tile_m > 0.0:
            ground = self._tiled_ground()
        elif self.ground.periodic:
            ground = self._wrapped_ground()
        else:
            ground = self._box([h, h, 0.05], [1, 1, 1, 1], 0.0)
        tex = pb.loadTexture(str(self.ground.png()), physicsClientId=c)
        if tex < 0:
            raise SimError("pybullet: could not load the ground texture")
        pb.changeVisualShape(ground, -1, textureUniqueId=tex, physicsClientId=c)

    def _build_pad(self) -> None:
        pad = self.pad
        if isinstance(pad, PadTexture):
            self._textured_pad(pad)
            return
        s = pad.side_m / 2
        self._box([s, s, 0.01], [*pad.green_rgb, 1], pad.square_top_m)
        a, w = pad.cross_length_m / 2, pad.cross_width_m / 2
        self._box([a, w, 0.01], [*pad.red_rgb, 1], pad.cross_top_m)
        self._box([w, a, 0.01], [*pad.red_rgb, 1], pad.cross_top_m)

    def _textured_pad(self, pad: PadTexture) -> None:
        """A picture pad: one textured quad of its true size, ``top_m`` above the ground."""
        c = self._client
        w, h = pad.size_m
        vertices, uvs = [], []
        for n, e in ((h / 2, -w / 2), (h / 2, w / 2), (-h / 2, w / 2), (-h / 2, -w / 2)):
            vertices.append(ned_to_scene((n, e, -pad.top_m)).tolist())
            # u runs east from the west edge; TinyRenderer reads a mesh's v bottom-up
            uvs.append([(e + w / 2) / w, (n + h / 2) / h])
        shape = pb.createVisualShape(
            pb.GEOM_MESH,
            vertices=vertices,
            indices=[0, 1, 2, 0, 2, 3, 0, 2, 1, 0, 3, 2],
            uvs=uvs,
            normals=[[0.0, 0.0, 1.0]] * 4,
            physicsClientId=c,
        )
        if shape < 0:
            raise SimError("pybullet: could not create the pad mesh")
        body = pb.createMultiBody(baseMass=0.0, baseVisualShapeIndex=shape, physicsClientId=c)
        tex = pb.loadTexture(str(pad.png()), physicsClientId=c)
        if tex < 0:
            raise SimError("pybullet: could not load the pad texture")
        pb.changeVisualShape(body, -1, textureUniqueId=tex, physicsClientId=c)

    def _wrapped_ground(self) -> int:
        """One mesh body for any periodic map (a ground image's rotated tile): the ground square
        cut into QUAD_M quads whose uvs run on past the tile's edges, each quad's shifted by
        whole tiles to near [0, 1) (TinyRenderer wraps uvs; the mirrored tile's texels either
        side of its edge are the same, so a rounding there shows nothing)."""
        g = self.ground
        h = self.GROUND_HALF_SIDE_M
        inv = np.linalg.inv(g.texel_to_ne)
        rows, cols = g.rgb.shape[:2]
        grid = np.arange(-h, h + 0.5 * self.QUAD_M, self.QUAD_M)
        n, e = np.meshgrid(grid, grid, indexing="ij")  # vertex (i, j): north i, east j
        col, row, _ = np.einsum("ij,jkl->ikl", inv, np.stack([n, e, np.ones_like(n)]))
        u, v = (col + 0.5) / cols, 1.0 - (row + 0.5) / rows  # TinyRenderer's v runs bottom-up
        k = len(grid)
        vertices, uvs, indices = [], [], []
        for i in range(k - 1):
            for j in range(k - 1):
                corners = ((i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1))
                du = math.floor(sum(u[c] for c in corners) / 4)
                dv = math.floor(sum(v[c] for c in corners) / 4)
                _add_quad(
                    (vertices, uvs, indices),
                    [(n[c], e[c]) for c in corners],
                    [(float(u[c] - du), float(v[c] - dv)) for c in corners],
                )
        return self._mesh(vertices, indices, uvs)

    def _mesh(self, vertices, indices, uvs) -> int:
        c = self._client
        shape = pb.createVisualShape(
            pb.GEOM_MESH,
            vertices=vertices,
            indices=indices,
            uvs=uvs,
            normals=[[0.0, 0.0, 1.0]] * len(vertices),
            physicsClientId=c,
        )
        if shape < 0:
            raise SimError("pybullet: could not create the ground mesh")
        return pb.createMultiBody(baseMass=0.0, baseVisualShapeIndex=shape, physicsClientId=c)

    def _tiled_ground(self) -> int:
        """One mesh body: the ground square cut into quads at the tile edges (z = 0)."""
        g = self.ground
        h = self.GROUND_HALF_SIDE_M
        inv = np.linalg.inv(g.texel_to_ne)
        rows, cols = g.rgb.shape[:2]

        def uv(n: float, e: float) -> tuple[float, float]:
            col, row, _ = inv @ (n, e, 1.0)
            # texel centre k <-> u = (k + .5)/W; TinyRenderer reads a mesh's v bottom-up
            return (col + 0.5) / cols, 1.0 - (row + 0.5) / rows

        def cuts(axis_origin: float, step: float) -> list[float]:
            k0 = math.floor((-h - axis_origin) / step)
            pts = [axis_origin + k * step for k in range(k0, k0 + int(2 * h / step) + 3)]
            # plus a cut every QUAD_M: TinyRenderer interpolates uvs in single precision, and
            # smaller quads keep its texel lookups on the map's grid near the camera
            grid = np.arange(-h, h, self.QUAD_M)
            return sorted({-h, h, *[p for p in pts if -h < p < h], *grid.tolist()})

        # tile edges: where (col + 0.5) or (row + 0.5) is a multiple of the tile size
        n_origin = float(g.texel_to_ne[0, 2] - 0.5 * g.texel_to_ne[0, 0])
        e_origin = float(g.texel_to_ne[1, 2] - 0.5 * g.texel_to_ne[1, 1])
        ns, es = cuts(n_origin, g.tile_m), cuts(e_origin, g.tile_m)
        vertices, uvs, indices = [], [], []
        for n0, n1 in itertools.pairwise(ns):
            for e0, e1 in itertools.pairwise(es):
                nm, em = (n0 + n1) / 2, (e0 + e1) / 2
                # this quad's tile: uv of its centre, shifted into [0, 1)
                u_c, v_c = uv(nm, em)
                du, dv = math.floor(u_c), math.floor(v_c)
                corners = ((n0, e0), (n1, e0), (n1, e1), (n0, e1))
                corner_uvs = [uv(n, e) for n, e in corners]
                _add_quad(
                    (vertices, uvs, indices), corners, [(u - du, v - dv) for u, v in corner_uvs]
                )
        return self._mesh(vertices, indices, uvs)

    def render(self, pos_ned_m, quat_wxyz, cfg: CameraConfig, time_s: float = 0.0) -> np.ndarray:
        """Noise-free mono8 image (height, width) from a camera at the vehicle's pose, at sim
        time ``time_s`` (where a moving pad is)."""
        return luma(self.render_rgb(pos_ned_m, quat_wxyz, cfg, time_s))

    def render_rgb(
        self, pos_ned_m, quat_wxyz, cfg: CameraConfig, time_s: float = 0.0
    ) -> np.ndarray:
        """Noise-free colour image (height, width, 3) uint8, row 0 = body forward."""
        if self._site is not None:
            self._site.place(time_s)
        rot = quat_to_rotation(quat_wxyz)
        eye = ned_to_scene(pos_ned_m)
        look = ned_to_scene(rot[:, 2])  # body +z (down) in the scene
        up = ned_to_scene(rot[:, 0])  # body +x (forward) is image up
        c = self._client
        view = pb.computeViewMatrix(
            cameraEyePosition=eye.tolist(),
            cameraTargetPosition=(eye + look).tolist(),
            cameraUpVector=up.tolist(),
            physicsClientId=c,
        )
        altitude = max(0.0, -float(pos_ned_m[2]))
        near = 0.02
        far = max(50.0, 4.0 * altitude + 50.0)
        proj = pb.computeProjectionMatrixFOV(
            fov=cfg.fov_deg,
            aspect=cfg.width_px / cfg.height_px,
            nearVal=near,
            farVal=far,
            physicsClientId=c,
        )
        _, _, rgba, _, _ = pb.getCameraImage(
            cfg.width_px,
            cfg.height_px,
            viewMatrix=view,
            projectionMatrix=proj,
            renderer=pb.ER_TINY_RENDERER,
            flags=pb.ER_NO_SEGMENTATION_MASK,
            shadow=0,
            lightDirection=[0.0, 0.0, 1.0],
            lightAmbientCoeff=0.7,
            lightDiffuseCoeff=0.3,
            lightSpecularCoeff=0.0,
            physicsClientId=c,
        )
        return np.asarray(rgba, dtype=np.uint8).reshape(cfg.height_px, cfg.width_px, 4)[..., :3]

    def close(self) -> None:
        if self._client >= 0:
            pb.disconnect(physicsClientId=self._client)
            self._client = -1

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Camera:
    """The downward camera: a renderer's image, the episode's light and camera effects
    (:class:`sitl_sim.render.visual.CameraEffects`, none in the nominal world), then seeded sensor
    noise."""

    def __init__(
        self,
        scene: Renderer,
        cfg: CameraConfig,
        rng: np.random.Generator,
        light: float = 1.0,
        effects: CameraEffects | None = None,
    ) -> None:
        self._scene = scene
        self._cfg = cfg
        self._rng = rng
        self._light = float(light)
        self._effects = effects

    @property
    def config(self) -> CameraConfig:
        return self._cfg

    def focal_px(self) -> float:
        """Pinhole focal length in pixels (square pixels, ``fov_deg`` across the height)."""
        return 0.5 * self._cfg.height_px / math.tan(math.radians(self._cfg.fov_deg) / 2)

    def capture(
        self, pos_ned_m, quat_wxyz, rate_frd_rad_s=(0.0, 0.0, 0.0), time_s: float = 0.0
    ) -> np.ndarray:
        """The frame from the vehicle's pose at sim time ``time_s`` (where a moving pad is)."""
        img = self._scene.render(pos_ned_m, quat_wxyz, self._cfg, time_s)
        if self._light != 1.0:
            img = cv2.convertScaleAbs(img, alpha=self._light)
        if self._effects is not None:
            img = self._effects.apply(img, pos_ned_m, quat_to_rotation(quat_wxyz), rate_frd_rad_s)
        sigma = self._cfg.noise_std_px
        if sigma > 0:
            noise = self._rng.standard_normal(img.shape, dtype=np.float32)
            noisy = img.astype(np.float32) + np.float32(sigma) * noise
            img = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
        return img
