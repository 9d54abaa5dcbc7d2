"""``visland pad acquire``: from how high the model acquires a pad on a full-resolution camera,
with and without the region of interest (:mod:`companion.roi`).

The simulator's fast renderer draws the pad on each ground (the nominal ground and terrain
families, sun overhead) from a grid of altitudes, the pad at a random bearing inside the
policy's 45° view, the vehicle tilted a few degrees and turned at random, with the camera's
sensor noise. The model's CNN (:meth:`perceive`) then looks at each frame as:

* ``native`` — the simulator's own 128 px, 45° camera (the images the CNN was trained on);
* ``crop`` — the full frame's centred 45° square area-resized to 128 px: a full-resolution
  camera without ROI (:func:`companion.camera.fit_to_policy`, what the companion does today);
* ``track`` — the ROI window around the pad as the estimator would predict it (the true pad
  plus a Gaussian horizontal error of ``predict_sigma_m``, the window sized for that
  uncertainty): the pad held once found (:meth:`companion.roi.RoiConfig.track_window`);
* ``search`` — the ROI's search, no estimate yet (:meth:`companion.roi.RoiConfig.search_window`
  at the true altitude): found if any of the tiles that hold the whole pad detects it (a sweep
  visits each), or where the pad is wider than half a tile, if the 45° view (the crop) does;
  ``false_alarms`` counts detections in tiles without the pad (three tiles per frame).

With ``flights``, the same model also flies episodes of ``scenario`` (a 1 m pad from 30-50 m)
in process on each camera — ``native``, ``crop`` and ``roi`` (the full policy loop: search,
track, the window cut by :class:`sitl_sim.full_res.FullResSimulator`) — and reports the
altitude of the first horizontal fix, success and landing error.

A frame counts as a detection when the pad probability is at least the checkpoint's
``visibility_threshold`` (0.9 for the shipped model); the bearing error is the angle between
the (mapped) bearing and the true one, over detections. A mode's **acquisition altitude** is
the highest altitude of the grid up to which (from the lowest) at least ``need`` (90 %) of the
frames are detections.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

__all__ = ["AcquireConfig", "acquire", "format_acquire"]

MODES = ("native", "crop", "track", "search")


@dataclass(frozen=True)
class AcquireConfig:
    """What ``visland pad acquire`` renders and measures."""

    pad: str = "helipad_1m"
    checkpoint: str | None = None
    width_px: int = 640
    height_px: int = 480
    hfov_deg: float = 62.2
    altitudes_m: tuple[float, ...] = tuple(float(a) for a in range(10, 65, 5))
    frames: int = 8
    """Frames per altitude and ground (random bearings and attitudes)."""
    grounds: tuple[str, ...] = ("nominal", "grass", "asphalt", "gravel", "sand", "regolith")
    span_px: float = 24.0
    tile_px: int = 128
    predict_sigma_m: float = 0.5
    tilt_deg: float = 5.0
    noise_std_px: float = 2.0
    need: float = 0.9
    seed: int = 0
    flights: int = 0
    """Closed-loop flights per camera (0: none): ``scenario``'s episodes of seed ``seed``."""
    scenario: str = "configs/scenario_field.toml"


def _camera_cfgs(cfg: AcquireConfig):
    from sitl_sim.config import CameraConfig

    f = (cfg.width_px / 2.0) / math.tan(math.radians(cfg.hfov_deg) / 2.0)
    vfov = 2.0 * math.degrees(math.atan(cfg.height_px / 2.0 / f))
    full = CameraConfig(cfg.width_px, cfg.height_px, vfov, cfg.noise_std_px, "fast")
    native = CameraConfig(128, 128, 45.0, cfg.noise_std_px, "fast")
    return full, native


def _ground(name: str, seed: int):
    from sitl_sim.render.ground import nominal_ground
    from sitl_sim.render.terrain import Sun, terrain_map

    return nominal_ground() if name == "nominal" else terrain_map(name, seed, Sun(90.0, 0.0))


def _pose(rng: np.random.Generator, alt: float, tilt_deg: float, max_tan: float):
    """A vehicle pose ``alt`` above the pad (NED origin) that sees it at a random bearing."""
    from sitl_sim.physics.dynamics import quat_from_euler, quat_to_rotation

    roll, pitch = np.radians(rng.uniform(-tilt_deg, tilt_deg, 2))
    yaw = rng.uniform(-math.pi, math.pi)
    quat = quat_from_euler(float(roll), float(pitch), float(yaw))
    tr, tf = rng.uniform(-max_tan, max_tan, 2)
    ray = quat_to_rotation(quat) @ np.array([tf, tr, 1.0])
    pos = np.array([-ray[0] * alt / ray[2], -ray[1] * alt / ray[2], -alt])
    return pos, quat


def _pad_in_body(pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    from sitl_sim.physics.dynamics import quat_to_rotation

    return quat_to_rotation(quat).T @ (-pos)


def _angle_deg(tr: float, tf: float, er: float, ef: float) -> float:
    a = np.array([tf, tr, 1.0])
    b = np.array([ef, er, 1.0])
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def _tile_holds(tile, u: float, v: float, half: float) -> bool:
    x0, y0, n = tile.x0, tile.y0, tile.side
    return x0 <= u - half and u + half <= x0 + n - 1 and y0 <= v - half and v + half <= y0 + n - 1


class _Tally:
    """Detections and bearing errors per altitude of one mode."""

    def __init__(self, altitudes: tuple[float, ...]) -> None:
        self.hits = {a: [] for a in altitudes}
        self.errors = {a: [] for a in altitudes}

    def add(self, alt: float, detected: bool, error_deg: float | None) -> None:
        self.hits[alt].append(bool(detected))
        if detected and error_deg is not None:
            self.errors[alt].append(error_deg)

    def report(self, need: float) -> dict[str, Any]:
        rows = []
        acquire = None
        holding = True
        for alt in sorted(self.hits):
            rate = float(np.mean(self.hits[alt])) if self.hits[alt] else math.nan
            err = self.errors[alt]
            rows.append(
                {
                    "altitude_m": alt,
                    "frames": len(self.hits[alt]),
                    "detected": rate,
                    "bearing_error_deg_median": float(np.median(err)) if err else None,
                    "bearing_error_deg_p95": float(np.percentile(err, 95)) if err else None,
                }
            )
            holding = holding and rate >= need
            if holding:
                acquire = alt
        every = [e for a in sorted(self.errors) for e in self.errors[a]]
        return {
            "acquire_altitude_m": acquire,
            "highest_detected_altitude_m": max(
                (r["altitude_m"] for r in rows if r["detected"] >= need), default=None
            ),
            "bearing_error_deg_median": float(np.median(every)) if every else None,
            "bearing_error_deg_p95": float(np.percentile(every, 95)) if every else None,
            "rows": rows,
        }


def acquire(cfg: AcquireConfig) -> dict[str, Any]:
    """Render, look and tally (see the module's docstring); one JSON-ready dict."""
    from companion.camera import fit_to_policy
    from companion.packaged import shipped_policy
    from companion.policy_net import CheckpointError
    from companion.roi import RoiConfig, cut
    from companion.runtime import load_policy_file
    from sitl_sim.full_res import camera_geometry
    from sitl_sim.render.render_fast import FastRenderer
    from sitl_sim.render.scene import Camera
    from tools.pad_info import resolve_pad

    _check(cfg)
    design = resolve_pad(cfg.pad)
    ckpt = Path(cfg.checkpoint) if cfg.checkpoint else shipped_policy()
    policy = load_policy_file(ckpt, torch_threads=1, runtime="torch")  # steady on busy cores
    if policy.privileged:
        raise CheckpointError(f"{ckpt}: a privileged policy has no CNN; give a vision checkpoint")
    threshold = float(policy.config.visibility_threshold)
    full_cfg, native_cfg = _camera_cfgs(cfg)
    w, h, fx, cx, cy = camera_geometry(full_cfg)
    pad_m = float(max(design.size_m))
    roi = RoiConfig(w, h, fx, cx, cy, pad_m=pad_m, span_px=cfg.span_px, tile_px=cfg.tile_px)
    tiles = roi.tiles()
    max_tan = 0.8 * math.tan(math.radians(22.5))
    tallies = {m: _Tally(cfg.altitudes_m) for m in MODES}
    false_alarms = [0, 0]  # detections, tiles looked at
    track_alarms = [0, 0]  # detections, track windows without the pad looked at
    sides: dict[float, list[int]] = {a: [] for a in cfg.altitudes_m}

    def look(image: np.ndarray) -> tuple[float, float, float]:
        tr, tf, logit = (float(v) for v in policy.perceive(image))
        return tr, tf, 1.0 / (1.0 + math.exp(-max(-30.0, min(30.0, logit))))

    renderer = FastRenderer(pad=design.scene_pad())
    for g_index, ground in enumerate(cfg.grounds):
        renderer.configure(_ground(ground, cfg.seed), design.scene_pad())
        rng = np.random.default_rng([cfg.seed, g_index])
        full_cam = Camera(renderer, full_cfg, np.random.default_rng([cfg.seed, g_index, 1]))
        native_cam = Camera(renderer, native_cfg, np.random.default_rng([cfg.seed, g_index, 2]))
        for alt in cfg.altitudes_m:
            for _ in range(cfg.frames):
                pos, quat = _pose(rng, alt, cfg.tilt_deg, max_tan)
                body = _pad_in_body(pos, quat)
                tr0, tf0 = body[1] / body[2], body[0] / body[2]
                frame = full_cam.capture(pos, quat)
                # native and crop: the 45° image as the CNN knows it
                for mode, image in (
                    ("native", native_cam.capture(pos, quat)),
                    ("crop", fit_to_policy(frame, fx, cx_px=cx, cy_px=cy)),
                ):
                    er, ef, vis = look(image)
                    tallies[mode].add(alt, vis >= threshold, _angle_deg(tr0, tf0, er, ef))
                    if mode == "crop":
                        in_view = _angle_deg(tr0, tf0, er, ef) if vis >= threshold else None
                # track: the window around the predicted pad, its bearing mapped back
                err_ne = rng.normal(0.0, cfg.predict_sigma_m, 2)
                predicted = body + _rotation_of(quat).T @ np.array([err_ne[0], err_ne[1], 0.0])
                window = roi.track_window(predicted, cfg.predict_sigma_m)
                sides[alt].append(window.side)
                er, ef, vis = window.to_camera(np.array(look(cut(frame, window))))
                tallies["track"].add(alt, vis >= threshold, _angle_deg(tr0, tf0, er, ef))
                # the same window where the pad is not (an estimate gone wrong): no detection
                away = _away(roi, window, cx + fx * tr0, cy - fx * tf0, 0.5 * fx * pad_m / body[2])
                if away is not None:
                    track_alarms[0] += look(cut(frame, away))[2] >= threshold
                    track_alarms[1] += 1
                # search: the tiles that hold the whole pad; a few without it for false alarms
                u, v = cx + fx * tr0, cy - fx * tf0
                half = 0.5 * fx * pad_m / body[2]
                holding = [t for t in tiles if _tile_holds(t, u, v, half)]
                # the search's window at this altitude: the view (the crop) or the tiles
                use_view = roi.search_window(0, float(body[2])).kind == "view"
                best = in_view if use_view else None
                for tile in () if use_view else holding:
                    er, ef, vis = tile.to_camera(np.array(look(cut(frame, tile))))
                    if vis >= threshold:
                        best = _angle_deg(tr0, tf0, er, ef)
                        break
                tallies["search"].add(alt, best is not None, best)
                far = [t for t in tiles if not _tile_holds(t, u, v, -half - 2.0)]
                for k in rng.choice(len(far), size=min(3, len(far)), replace=False):
                    false_alarms[0] += look(cut(frame, far[int(k)]))[2] >= threshold
                    false_alarms[1] += 1
    out: dict[str, Any] = {
        "pad": design.name,
        "pad_m": pad_m,
        "checkpoint": str(ckpt),
        "threshold": threshold,
        "need": cfg.need,
        "camera": {"width_px": w, "height_px": h, "hfov_deg": cfg.hfov_deg, "fx_px": fx},
        "config": asdict(cfg),
        "modes": {m: tallies[m].report(cfg.need) for m in MODES},
        "search": {
            "tiles": len(tiles),
            "tile_px": cfg.tile_px,
            "sweep_frames": len(tiles),
            "false_alarms": int(false_alarms[0]),
            "tiles_without_pad": int(false_alarms[1]),
        },
        "track_false_alarms": int(track_alarms[0]),
        "track_windows_without_pad": int(track_alarms[1]),
        "track_window_side_px": {str(a): float(np.median(s)) for a, s in sides.items() if s},
    }
    if cfg.flights > 0:
        out["flights"] = {m: _fly(cfg, policy, m, pad_m) for m in ("native", "crop", "roi")}
    return out


def _fly(cfg: AcquireConfig, policy: Any, camera: str, pad_m: float) -> dict[str, Any]:
    """``cfg.flights`` episodes of ``cfg.scenario`` flown in process on ``camera``: ``native``
    (the 128 px sim camera), ``crop`` (the full-resolution camera's 45° crop) or ``roi``."""
    import dataclasses

    from companion.roi import RoiConfig, roi_window
    from sitl_sim.config import load_sim
    from sitl_sim.env import LandingEnv
    from sitl_sim.full_res import FullResSimulator, camera_geometry
    from sitl_sim.metrics import EpisodeResult

    sim_cfg = load_sim()
    if camera != "native":
        full, _ = _camera_cfgs(cfg)
        sim_cfg = dataclasses.replace(sim_cfg, camera=dataclasses.replace(full, renderer="fast"))
    env = LandingEnv(sim=sim_cfg, scenario=cfg.scenario)
    rows = []
    try:
        if camera == "roi":
            policy.roi = RoiConfig(*camera_geometry(env.sim_config.camera), pad_m=pad_m)
        steps_max = math.ceil(env.sim_config.episode_timeout_s * env.sim_config.control_rate_hz)
        for index in range(cfg.flights):
            env.reset(seed=cfg.seed, options={"episode_index": index})
            sim = env.simulator
            state = policy.initial_state()
            truth = sim.ground_truth()
            start_alt, fix_alt, result = -float(truth.pos_ned_m[2]), None, None
            for step in range(steps_max):
                if isinstance(sim, FullResSimulator):
                    sim.aim(roi_window(state))  # None (ROI off): the 45° crop
                command, state = policy.act(sim.observe(frame_id=step, truth=truth), truth, state)
                if fix_alt is None and bool(np.all(state.estimator.initialised[:2])):
                    fix_alt = -float(truth.pos_ned_m[2])
                contact = sim.step(command)
                truth = sim.ground_truth()
                if contact is not None:
                    result = EpisodeResult.from_contact(contact)
                    break
            if result is None:
                result = EpisodeResult.timeout(truth.time_s, *truth.pad_relative)
            rows.append(
                {
                    "episode_index": index,
                    "start_altitude_m": start_alt,
                    "first_fix_altitude_m": fix_alt,
                    "success": bool(result.success),
                    "landing_error_m": float(result.landing_error_m),
                }
            )
    finally:
        policy.roi = None
        env.close()
    fixes = [r["first_fix_altitude_m"] for r in rows if r["first_fix_altitude_m"] is not None]
    errors = [r["landing_error_m"] for r in rows]
    return {
        "success_rate": sum(r["success"] for r in rows) / len(rows),
        "first_fix_altitude_m_median": float(np.median(fixes)) if fixes else None,
        "first_fix_fraction_of_start_median": float(
            np.median(
                [
                    r["first_fix_altitude_m"] / r["start_altitude_m"]
                    for r in rows
                    if r["first_fix_altitude_m"] is not None
                ]
            )
        )
        if fixes
        else None,
        "landing_error_m_median": float(np.median(errors)),
        "landing_error_m_max": float(np.max(errors)),
        "episodes": rows,
    }


def _away(roi, window, u: float, v: float, half: float):
    """``window`` moved a window and a half off the pad (the first such place in the frame
    that does not hold any of it), or None."""
    n = window.side
    for dx, dy in ((1.5, 0), (-1.5, 0), (0, 1.5), (0, -1.5), (1.5, 1.5), (-1.5, -1.5)):
        moved = roi.window(window.x0 + dx * n, window.y0 + dy * n, n, "track")
        if not _tile_holds(moved, u, v, -half - 2.0):
            return moved
    return None


def _check(cfg: AcquireConfig) -> None:
    """Raises ConfigError naming the option and what it expects."""
    from sitl_sim.errors import ConfigError
    from sitl_sim.render.terrain import FAMILIES

    known = ["nominal", *sorted(FAMILIES)]
    bad = [g for g in cfg.grounds if g not in known]
    if bad or not cfg.grounds:
        raise ConfigError(f"--grounds {list(cfg.grounds)}: expected some of {known}")
    if not cfg.altitudes_m or not all(math.isfinite(a) and a > 1.0 for a in cfg.altitudes_m):
        raise ConfigError(f"--altitudes {list(cfg.altitudes_m)}: expected metres > 1")
    if cfg.frames < 1:
        raise ConfigError(f"--frames {cfg.frames}: expected >= 1")
    if cfg.flights < 0:
        raise ConfigError(f"--flights {cfg.flights}: expected >= 0")
    if min(cfg.width_px, cfg.height_px) < 128:
        raise ConfigError(f"--camera {cfg.width_px}x{cfg.height_px}: expected >= 128x128 px")


def _rotation_of(quat: np.ndarray) -> np.ndarray:
    from sitl_sim.physics.dynamics import quat_to_rotation

    return quat_to_rotation(quat)


def format_acquire(res: dict[str, Any], out: TextIO) -> None:
    """The human-readable table of :func:`acquire`."""
    cam = res["camera"]
    print(
        f"pad {res['pad']} ({res['pad_m']:g} m) on a {cam['width_px']}x{cam['height_px']} "
        f"camera, {cam['hfov_deg']:g} deg wide; detection: visibility >= {res['threshold']:g} "
        f"in >= {100 * res['need']:.0f} % of frames",
        file=out,
    )
    names = {
        "native": "128 px sim camera (reference)",
        "crop": "full frame -> 45 deg crop (no ROI)",
        "track": "ROI track window",
        "search": "ROI search tiles",
    }
    for mode, rep in res["modes"].items():
        alt = rep["acquire_altitude_m"]
        err = rep["bearing_error_deg_median"]
        print(
            f"  {names[mode]:36s} acquires up to {'-' if alt is None else f'{alt:g} m':>6}"
            f"   bearing error median {'-' if err is None else f'{err:.2f} deg'}",
            file=out,
        )
    alts = [r["altitude_m"] for r in res["modes"]["crop"]["rows"]]
    print("  altitude  " + "  ".join(f"{m:>7}" for m in res["modes"]), file=out)
    for i, alt in enumerate(alts):
        rates = "  ".join(f"{res['modes'][m]['rows'][i]['detected']:7.2f}" for m in res["modes"])
        print(f"  {alt:6g} m  {rates}", file=out)
    s = res["search"]
    print(
        f"  search: {s['tiles']} tiles of {s['tile_px']} px (a sweep: {s['sweep_frames']} "
        f"frames); false alarms {s['false_alarms']} of "
        f"{s['tiles_without_pad']} tiles without the pad",
        file=out,
    )
    print(
        f"  track windows moved off the pad: {res['track_false_alarms']} detections of "
        f"{res['track_windows_without_pad']}",
        file=out,
    )
    for camera, rep in res.get("flights", {}).items():
        fix = rep["first_fix_altitude_m_median"]
        print(
            f"  flights, {camera:6s}: success {100 * rep['success_rate']:.0f} % of "
            f"{len(rep['episodes'])}, first fix at {'-' if fix is None else f'{fix:.1f} m'} "
            f"(median), landing error median {rep['landing_error_m_median']:.2f} m, max "
            f"{rep['landing_error_m_max']:.2f} m",
            file=out,
        )
