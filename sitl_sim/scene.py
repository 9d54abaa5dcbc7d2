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

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as pb

from sitl_sim.config import CameraConfig
from sitl_sim.dynamics import quat_to_rotation
from sitl_sim.errors import SimError

__all__ = ["Camera", "PadGeometry", "Scene", "ned_to_scene"]

_NED_TO_SCENE = np.diag([1.0, -1.0, -1.0])
_LUMA_Q8 = (77, 150, 29)  # ITU-R BT.601 luma weights 0.299, 0.587, 0.114 in 1/256ths


def ned_to_scene(v_ned) -> np.ndarray:
    """A NED vector or point in pybullet's NWU world."""
    return _NED_TO_SCENE @ np.asarray(v_ned, dtype=float)


@dataclass(frozen=True)
class PadGeometry:
    """The paper's landing target: a red cross on a green square, centred on the origin."""

    side_m: float = 4.0
    cross_length_m: float = 3.2
    cross_width_m: float = 0.6
    green_rgb: tuple[float, float, float] = (0.25, 0.85, 0.25)
    red_rgb: tuple[float, float, float] = (0.80, 0.08, 0.08)


class Scene:
    """A pybullet DIRECT client holding the ground and the pad. Close it (or use ``with``)."""

    GROUND_HALF_SIDE_M = 300.0
    TEXTURE_PX = 1024

    def __init__(self, pad: PadGeometry | None = None, texture_seed: int = 7) -> None:
        self.pad = pad or PadGeometry()
        self._client = pb.connect(pb.DIRECT)
        if self._client < 0:
            raise SimError("pybullet: could not open a DIRECT client")
        try:
            self._build(texture_seed)
        except Exception:
            pb.disconnect(physicsClientId=self._client)
            raise

    @property
    def client_id(self) -> int:
        return self._client

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

    def _build(self, texture_seed: int) -> None:
        c = self._client
        h = self.GROUND_HALF_SIDE_M
        ground = self._box([h, h, 0.05], [1, 1, 1, 1], 0.0)
        tex = pb.loadTexture(str(_ground_texture(texture_seed, self.TEXTURE_PX)), physicsClientId=c)
        if tex < 0:
            raise SimError("pybullet: could not load the ground texture")
        pb.changeVisualShape(ground, -1, textureUniqueId=tex, physicsClientId=c)
        pad = self.pad
        s = pad.side_m / 2
        self._box([s, s, 0.01], [*pad.green_rgb, 1], 0.02)
        a, w = pad.cross_length_m / 2, pad.cross_width_m / 2
        self._box([a, w, 0.01], [*pad.red_rgb, 1], 0.04)
        self._box([w, a, 0.01], [*pad.red_rgb, 1], 0.04)

    def render(self, pos_ned_m, quat_wxyz, cfg: CameraConfig) -> np.ndarray:
        """Noise-free mono8 image (height, width) from a camera at the vehicle's pose."""
        rgb = self.render_rgb(pos_ned_m, quat_wxyz, cfg).astype(np.uint16)
        r, g, b = _LUMA_Q8
        return ((r * rgb[..., 0] + g * rgb[..., 1] + b * rgb[..., 2] + 128) >> 8).astype(np.uint8)

    def render_rgb(self, pos_ned_m, quat_wxyz, cfg: CameraConfig) -> np.ndarray:
        """Noise-free colour image (height, width, 3) uint8, row 0 = body forward."""
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
    """The downward camera: a :class:`Scene` render plus seeded sensor noise."""

    def __init__(self, scene: Scene, cfg: CameraConfig, rng: np.random.Generator) -> None:
        self._scene = scene
        self._cfg = cfg
        self._rng = rng

    @property
    def config(self) -> CameraConfig:
        return self._cfg

    def focal_px(self) -> float:
        """Pinhole focal length in pixels (square pixels, ``fov_deg`` across the height)."""
        return 0.5 * self._cfg.height_px / math.tan(math.radians(self._cfg.fov_deg) / 2)

    def capture(self, pos_ned_m, quat_wxyz) -> np.ndarray:
        img = self._scene.render(pos_ned_m, quat_wxyz, self._cfg)
        sigma = self._cfg.noise_std_px
        if sigma > 0:
            noise = self._rng.standard_normal(img.shape, dtype=np.float32)
            noisy = img.astype(np.float32) + np.float32(sigma) * noise
            img = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
        return img


def _ground_texture(seed: int, size: int) -> Path:
    """A deterministic, terrain-like PNG texture (multi-octave value noise), cached on disk."""
    from PIL import Image

    path = Path(tempfile.gettempdir()) / f"visland_ground_v2_{seed}_{size}.png"
    if path.exists():
        return path
    rng = np.random.default_rng(seed)
    field = np.zeros((size, size))
    for octave, weight in ((8, 1.0), (32, 0.6), (128, 0.35), (512, 0.2)):
        coarse = rng.random((octave, octave))
        reps = size // octave
        field += weight * np.kron(coarse, np.ones((reps, reps)))
    field = (field - field.min()) / (np.ptp(field) + 1e-9)
    # Dry, reddish-brown terrain (Mars-like): in mono8 always darker than the pad's green.
    base = np.array([100.0, 80.0, 65.0])
    rgb = base[None, None, :] * (0.6 + 0.8 * field[..., None])
    tmp = path.with_suffix(f".{rng.integers(1 << 30)}.tmp.png")
    Image.fromarray(np.clip(rgb, 0, 255).astype(np.uint8), "RGB").save(tmp)
    tmp.replace(path)  # atomic: parallel workers never read a half-written file
    return path
