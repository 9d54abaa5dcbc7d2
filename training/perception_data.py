"""Pose-sampled camera frames for perception training, rendered by the simulator's own camera.

Expert flights keep the pad near the image centre, nearly level, and reach low altitude only
when already over the pad, so a CNN trained on them alone never sees the frames where a vision
policy gets into trouble: a tilted vehicle whose pad has left the view (it answers "pad straight
below, visible" and the estimator jumps tens of metres) or a low vehicle beside the pad (the view
is all cross arm and it answers "centred"). This module renders those frames on purpose.

Each sample draws an attitude, an altitude (log-uniform, so the last metres are as well covered
as the first hundred) and the bearing at which the pad centre should appear — inside the view for
most samples, outside it for the rest — and places the vehicle where that bearing holds. Labels
come from the same :func:`training.train.bearing_labels` as flight frames. Images go through
:class:`sitl_sim.render.scene.Camera` (the configured renderer + the configured pixel noise), the
camera
that flies, and are cached as one ``.npz`` per (seed, count) in the run folder.

With ``visuals`` (the ``[visual]`` sections of a run's training worlds), every chunk of
:data:`CHUNK` frames is rendered in a world drawn from them by weight — its ground family and
texture seed, sun, pad, haze and camera effects (``VisualConfig.draw(seed, chunk)``) — so the CNN
learns the pad on every ground and in every light the worlds fly, not only in the frames the
expert happened to see. ``None`` stands for the nominal ground and camera. With ``pads`` (the
worlds' ``[pad]`` sections) the chunk's pad is that world's design, drawn and carried as
:func:`sitl_sim.world.episode_world` draws an episode's, so the frames show the pad the worlds
fly (without them, the paper's pad). With ``terrains`` (the worlds' ``[terrain]`` sections) a
world whose site is not a still pad on flat ground — a rover, a deck, a slope, rocks — is drawn as
:func:`sitl_sim.world.episode_site` draws an episode's, at its time 0, and the frames show the
pad where it lies in it, with the vehicle that carries it (a rover's cab beside the pad, a ship's
deckhouse, the water) and the relief around it: a CNN that has never seen a cab beside the pad
takes the pair for the pad and answers a metre or two towards the cab. The poses stay relative
to the pad's centre (the labels); a camera that would sit less than half a metre above the
ground under it is lifted along its ray to the pad.
"""

from __future__ import annotations

import math
import multiprocessing as mp
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from sitl_sim.config import CameraConfig
from sitl_sim.physics.dynamics import quat_from_euler, quat_to_rotation
from sitl_sim.render.ground import PadGeometry, nominal_ground
from sitl_sim.render.pad_section import PadConfig
from sitl_sim.render.scene import Camera, make_renderer
from sitl_sim.render.visual import CameraEffects, VisualConfig, VisualSample
from sitl_sim.site.site import Site
from sitl_sim.site.terrain import TerrainConfig
from sitl_sim.world import episode_site

CHUNK = 256
"""Frames per rendering job, and per drawn visual world."""

__all__ = [
    "PoseSampling",
    "chunk_pad_frame",
    "has_site",
    "render_pose_frames",
    "sample_poses",
    "site_weights",
]


@dataclass(frozen=True)
class PoseSampling:
    """The distribution of rendered poses."""

    altitude_m: tuple[float, float] = (1.0, 110.0)
    """Log-uniform altitude range (the scenario starts at 75–100 m). Below ~1 m the view is a
    fraction of one cross arm and no image can tell where the centre is: those last metres are
    flown on the estimator's prediction."""
    in_view_fraction: float = 0.8
    """Share of samples whose pad centre is inside the view (the rest: outside, label 0)."""
    out_of_view_tan: float = 1.0
    """Out-of-view samples put the pad centre at a bearing up to this tangent."""
    level_fraction: float = 0.6
    """Share of nearly level samples (|roll|, |pitch| <= ``level_tilt_deg``)."""
    level_tilt_deg: float = 8.0
    max_tilt_deg: float = 35.0
    """The other samples: roll and pitch uniform in ± this (a recovering learner tilts a lot)."""
    away_fraction: float = 0.0
    """Share of samples with the pad far off (label 0): the camera ``away_m`` from the pad
    horizontally, at a drawn altitude and attitude, over ground with no pad in it — what a
    vehicle that has not found the pad, or has been blown off it, looks at. The out-of-view
    samples above keep the pad just outside the frame; without these a CNN never learns that
    bare ground is not a pad, and one trained on cabs, hulls and rocks beside pads finds pads in
    it."""
    away_m: tuple[float, float] = (40.0, 300.0)
    """Horizontal distance of the camera from the pad in the far-off samples (uniform)."""

    def key(self) -> dict:
        """The fields for a frame cache's key; without far-off samples, as before they
        existed (the caches made then stay valid)."""
        out = asdict(self)
        if self.away_fraction == 0.0:
            del out["away_fraction"], out["away_m"]
        return out


def sample_poses(
    n: int, seed: int, fov_deg: float, sampling: PoseSampling = PoseSampling()
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` camera poses: positions (n, 3) NED relative to the pad and quaternions (n, 4)."""
    rng = np.random.default_rng(seed)
    half = math.tan(math.radians(fov_deg) / 2)
    lo, hi = (math.log(a) for a in sampling.altitude_m)
    pos = np.zeros((n, 3))
    quat = np.zeros((n, 4))
    i = 0
    while i < n:
        away = sampling.away_fraction > 0 and rng.random() < sampling.away_fraction
        tilt = (
            sampling.level_tilt_deg
            if rng.random() < sampling.level_fraction
            else sampling.max_tilt_deg
        )
        roll, pitch = np.radians(rng.uniform(-tilt, tilt, 2))
        yaw = rng.uniform(-math.pi, math.pi)
        q = quat_from_euler(roll, pitch, yaw)
        if away:
            far = _away_pose(rng, q, half, lo, hi, sampling.away_m)
            if far is None:
                continue
            pos[i], quat[i] = far, q
            i += 1
            continue
        if rng.random() < sampling.in_view_fraction:
            tan = rng.uniform(-half, half, 2)
        else:
            tan = rng.uniform(-sampling.out_of_view_tan, sampling.out_of_view_tan, 2)
            if np.all(np.abs(tan) < half):
                continue
        # the pad lies along body (tan_forward, tan_right, 1): place the vehicle on that ray
        ray = quat_to_rotation(q) @ np.array([tan[1], tan[0], 1.0])
        if ray[2] < 0.1:
            continue  # looking at the horizon: no such frame in a landing
        alt = math.exp(rng.uniform(lo, hi))
        pos[i] = -ray * (alt / ray[2])
        quat[i] = q
        i += 1
    return pos, quat


def _away_pose(
    rng: np.random.Generator,
    q: np.ndarray,
    half: float,
    log_lo: float,
    log_hi: float,
    away_m: tuple[float, float],
) -> np.ndarray | None:
    """A far-off sample's position relative to the pad (attitude ``q``), or None where the pad
    would be in view after all (a high camera, a tilt towards it)."""
    alt = math.exp(rng.uniform(log_lo, log_hi))
    dist = rng.uniform(*away_m)
    bearing = rng.uniform(-math.pi, math.pi)
    pos = np.array([dist * math.cos(bearing), dist * math.sin(bearing), -alt])
    body = quat_to_rotation(q).T @ (-pos)
    if body[2] > 1e-6 and abs(body[0] / body[2]) < half and abs(body[1] / body[2]) < half:
        return None
    return pos


_WORKER: dict = {}


def _init(
    cfg: dict, seed: int, visuals: tuple, weights: tuple, pads: tuple, terrains: tuple
) -> None:
    camera = CameraConfig(**cfg)
    _WORKER["scene"] = make_renderer(camera.renderer)
    _WORKER["cfg"] = camera
    _WORKER["seed"] = seed
    _WORKER["visuals"] = visuals
    _WORKER["pads"] = pads
    _WORKER["terrains"] = terrains
    _WORKER["weights"] = np.asarray(weights, float) / float(np.sum(weights))


def _look(
    visual: VisualConfig | None, pad: PadConfig | None, seed: int, chunk: int
) -> VisualSample | None:
    """The look of chunk ``chunk`` as :func:`sitl_sim.world.episode_world` draws episode
    ``chunk`` of a world with these ``[visual]`` and ``[pad]`` sections: the visual draw carrying
    the pad's design (no ``[visual]``: the nominal look with the design); None: the nominal
    ground, camera and pad."""
    design = pad.draw(seed, chunk) if pad is not None else None
    if design is not None and (visual is not None or design.scene_pad() != PadGeometry()):
        return replace((visual or VisualConfig()).draw(seed, chunk), pad_design=design)
    return visual.draw(seed, chunk) if visual is not None else None


def _chunk_world(
    seed: int,
    chunk: int,
    visual: VisualConfig | None,
    pad: PadConfig | None,
    terrain: TerrainConfig | None,
) -> tuple[VisualSample | None, PadGeometry, Site | None]:
    """Chunk ``chunk``'s look (:func:`_look`), its pad's geometry and its site (None: a still
    pad on flat ground), drawn from one world's sections as an episode's are."""
    sample = _look(visual, pad, seed, chunk)
    look = sample.pad() if sample is not None else PadGeometry()
    return sample, look, episode_site(terrain, pad, seed, chunk, look)


def chunk_pad_frame(
    seed: int,
    chunk: int,
    visual: VisualConfig | None,
    pad: PadConfig | None,
    terrain: TerrainConfig | None,
) -> np.ndarray:
    """R_pad_to_ned (3, 3) of the pad in chunk ``chunk`` of :func:`render_pose_frames` (seed
    ``seed``) in a one-world run with these sections, at the frames' time 0: the axes a
    carried pad's error is read in (x: the carrier's nose). A still pad on flat ground:
    the identity (north, east, down)."""
    _, _, site = _chunk_world(seed, chunk, visual, pad, terrain)
    return np.eye(3) if site is None else np.asarray(site.pad_pose(0.0).R_pad_to_ned, float)


def _render_chunk(args: tuple[int, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The chunk's frames and its poses (relative to the pad; lifted where under the ground)."""
    chunk, pos, quat = args
    seed, cfg, scene = _WORKER["seed"], _WORKER["cfg"], _WORKER["scene"]
    rng = np.random.default_rng([seed, chunk])
    pick = np.random.default_rng([seed, chunk, 1])
    k = int(pick.choice(len(_WORKER["visuals"]), p=_WORKER["weights"]))
    sample, look, site = _chunk_world(
        seed, chunk, _WORKER["visuals"][k], _WORKER["pads"][k], _WORKER["terrains"][k]
    )
    origin = np.zeros(3)
    if site is not None:
        origin = np.asarray(site.pad_pose(0.0).position_ned, float)
        pos = np.array([_above_ground(site, p, origin) for p in pos])
    if sample is None:
        scene.configure(nominal_ground(), PadGeometry(), site)
        cam = Camera(scene, cfg, rng)
        rates = np.zeros((len(pos), 3))
    else:
        scene.configure(sample.ground(), look, site, sample.sun)
        effects = CameraEffects(sample, cfg, sample.light)
        cam = Camera(scene, cfg, rng, light=sample.light, effects=effects)
        rates = pick.uniform(-0.5, 0.5, (len(pos), 3))  # motion blur as a manoeuvre smears
    frames = [cam.capture(p + origin, q, r) for p, q, r in zip(pos, quat, rates, strict=True)]
    return np.stack(frames), pos


_CLEARANCE_M = 0.5


def _above_ground(site: Site, rel: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """``rel`` (the camera relative to the pad's centre ``origin``), moved out along its ray
    from the pad until it is :data:`_CLEARANCE_M` above the surface under it (a hillside, a
    rock, the cab): the bearing to the pad — its label — is kept."""
    out = np.array(rel, float)
    for _ in range(60):
        n, e, d = out + origin
        if -d - site.surface_height(float(n), float(e), 0.0) >= _CLEARANCE_M:
            break
        out *= 1.1
    return out


def has_site(pad: PadConfig | None, terrain: TerrainConfig | None) -> bool:
    """Whether a world with these ``[pad]`` and ``[terrain]`` sections draws a site: a pad
    carried by a rover or a deck, or ground that is not flat."""
    return terrain is not None or (pad is not None and not pad.still_on_ground)


def site_weights(
    shares: tuple[float, ...], sites: tuple[bool, ...], site_share: float | None
) -> tuple[float, ...]:
    """The worlds' ``shares`` rescaled so that the worlds with a site (``sites``) hold
    ``site_share`` of the whole and the others the rest, each group split by its shares;
    ``site_share`` None, or worlds all of one kind: the shares as they are."""
    if site_share is None or all(sites) or not any(sites):
        return tuple(shares)
    total = [sum(s for s, k in zip(shares, sites, strict=True) if k == want) for want in (0, 1)]
    part = (1.0 - site_share, site_share)
    return tuple(s * part[k] / total[k] for s, k in zip(shares, sites, strict=True))


def render_pose_frames(
    n: int,
    seed: int,
    camera: CameraConfig,
    cache_dir: str | Path | None = None,
    workers: int = 1,
    sampling: PoseSampling = PoseSampling(),
    visuals: tuple[VisualConfig | None, ...] = (None,),
    weights: tuple[float, ...] | None = None,
    pads: tuple[PadConfig | None, ...] | None = None,
    terrains: tuple[TerrainConfig | None, ...] | None = None,
    chunk: int = CHUNK,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` rendered frames: images (n, H, W) uint8, poses (n, 3) NED and quaternions (n, 4).

    ``visuals`` / ``weights``: the looks to render in, one drawn per chunk (module docstring);
    the default is the nominal ground and camera. ``pads``: each look's ``[pad]`` section (None:
    the paper's pad everywhere). ``terrains``: each look's ``[terrain]`` section (None: flat);
    with them and the pads, a look's site is drawn as an episode's (module docstring). With
    ``cache_dir`` the result is stored as
    ``poses_s<seed>_n<n>.npz`` and reloaded when its camera, sampling, visuals and pads match
    (its ``key``); a damaged cache file is rendered again. ``chunk``: frames per drawn look
    (fewer: more looks, sites and pads in as many frames).
    """
    if chunk < 1:
        raise ValueError(f"chunk = {chunk}; expected >= 1 frames per look")
    if not visuals:
        raise ValueError("visuals: expected at least one (None: the nominal look)")
    weights = tuple(weights) if weights is not None else (1.0,) * len(visuals)
    if len(weights) != len(visuals) or min(weights) <= 0:
        raise ValueError(f"weights {weights}: expected one positive weight per visual")
    pads = tuple(pads) if pads is not None else (None,) * len(visuals)
    if len(pads) != len(visuals):
        raise ValueError(f"pads: {len(pads)} sections; expected one per visual ({len(visuals)})")
    terrains = tuple(terrains) if terrains is not None else (None,) * len(visuals)
    if len(terrains) != len(visuals):
        raise ValueError(
            f"terrains: {len(terrains)} sections; expected one per visual ({len(visuals)})"
        )
    pos, quat = sample_poses(n, seed, camera.fov_deg, sampling)
    key = {
        "camera": asdict(camera),
        "sampling": sampling.key(),
        "visuals": [None if v is None else v.to_dict() for v in visuals],
        "weights": list(weights),
    }
    if chunk != CHUNK:  # (a key without it: the caches made before)
        key["chunk"] = chunk
    if any(pad is not None for pad in pads):  # (a key without pads: the caches made before)
        key["pads"] = [None if pad is None else _pad_key(pad) for pad in pads]
    sites = [has_site(p, t) for t, p in zip(terrains, pads, strict=True)]
    if any(sites):  # (likewise: a key without sites for the caches made before)
        key["sites"] = [
            [None if t is None else t.to_dict(), None if p is None else p.to_dict()]
            if site
            else None
            for t, p, site in zip(terrains, pads, sites, strict=True)
        ]
    path = Path(cache_dir) / f"poses_s{seed}_n{n}.npz" if cache_dir is not None else None
    if path is not None and path.exists():
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["key"]) == repr(key) and z["images"].shape[0] == n:
                    return z["images"], z["pos"], z["quat"]
        except (OSError, ValueError, KeyError):
            pass  # damaged or foreign cache: render again
    jobs = [(k, pos[s : s + chunk], quat[s : s + chunk]) for k, s in enumerate(range(0, n, chunk))]
    initargs = (asdict(camera), seed, tuple(visuals), weights, pads, terrains)
    if workers > 1:
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers, initializer=_init, initargs=initargs) as pool:
            parts = pool.map(_render_chunk, jobs)
    else:
        _init(*initargs)
        try:
            parts = [_render_chunk(j) for j in jobs]
        finally:
            _WORKER.pop("scene").close()
    if parts:
        images = np.concatenate([frames for frames, _ in parts])
        pos = np.concatenate([where for _, where in parts])
    else:
        images = np.zeros((0, camera.height_px, camera.width_px))
    images = images.astype(np.uint8)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, images=images, pos=pos, quat=quat, key=np.array(repr(key)))
        tmp.replace(path)
    return images, pos, quat


def _pad_key(pad: PadConfig) -> list[dict]:
    """What a ``[pad]`` section draws, for the cache key: each design's name, file, size and
    pattern or image."""
    return [
        {
            "name": d.name,
            "file": str(d.path) if d.path is not None else None,
            "size_m": list(d.size_m),
            "pattern": d.pattern,
            "image": str(d.image) if d.image is not None else None,
        }
        for d in pad.designs
    ]
