"""``visland log frame FILE [--time T] [--out PNG]``: one moment of a recorded flight as a PNG.

Left, the camera frame with the live view's annotations drawn on it — the very
``foxglove.ImageAnnotations`` that ``--live`` serves and ``visland log scene`` writes (the CNN's
bearing as a cross with its pad probability, the estimator's pad reprojected with its 2-sigma
circle). Right, the scene from above: the trajectory, the pad where it truly was (on its rover
or deck), the estimated pad with its 2-sigma ellipse, the camera's footprint on the ground and
the wind. Without ``--time`` the frame is the one where the estimate was furthest from the truth
(where a lost pad shows why), else the last. Matplotlib's Agg backend: no display needed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.contract import CAMERA_FOV_DEG
from companion.contract.messages import quat_to_rotation
from companion.flightlog import FlightLogError, read_log
from companion.live.frame import LiveFrame
from companion.live.replay import REPLAY_TOPICS, logged_frames, policy_of

__all__ = ["FrameReport", "plot_frame"]


@dataclass(frozen=True)
class FrameReport:
    out: str
    time_s: float
    """The frame drawn (the log's clock)."""
    frame: int
    """Its index among the log's camera frames."""
    frames: int
    why: str
    """How it was chosen."""
    estimate_error_m: float | None
    """Horizontal distance between the estimated and the true pad at that frame."""
    pad_probability: float | None
    altitude_m: float | None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _estimate_error(f: LiveFrame) -> float | None:
    if f.estimate_rel_ned_m is None or f.truth_rel_ned_m is None:
        return None
    d = np.asarray(f.estimate_rel_ned_m, float) - np.asarray(f.truth_rel_ned_m, float)
    return float(math.hypot(d[0], d[1]))


def _choose(frames: list[LiveFrame], time_s: float | None) -> tuple[int, str]:
    if time_s is not None:
        times = np.array([f.time_s for f in frames])
        i = int(np.argmin(np.abs(times - time_s)))
        return i, f"the frame nearest t = {time_s:g} s"
    errors = np.array([np.nan if e is None else e for e in map(_estimate_error, frames)])
    if np.isfinite(errors).any():
        # the last of the worst: a flight that lost the pad shows where it went on believing
        # it was, not the prior of its first frame
        worst = np.flatnonzero(errors >= 0.9 * np.nanmax(errors))
        return int(worst[-1]), "the estimate furthest from the truth (its last such frame)"
    return len(frames) - 1, "the last frame (no estimate against truth in this log)"


def plot_frame(
    path: str | Path,
    out: str | Path | None = None,
    time_s: float | None = None,
    policy: str | None = None,
) -> FrameReport:
    """Draw one frame of the flight log ``path`` (see the module docstring) to ``out`` (None:
    ``<stem>_frame.png`` beside it).

    Raises:
        FlightLogError: not a readable flight log, or it has no camera frames.
        ImportError: foxglove-sdk is not installed (the annotations are its messages).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    log = read_log(path, topics=set(REPLAY_TOPICS))
    name = policy_of(log, policy)
    loaded = None
    if name is not None:
        from companion.policy_net import load_policy

        loaded = load_policy(name)
    frames = [f for f in logged_frames(log, loaded) if isinstance(f, LiveFrame)]
    if not frames:
        raise FlightLogError(f"{path}: no /camera/image frames to draw")
    i, why = _choose(frames, time_s)
    f = frames[i]
    out = Path(out) if out is not None else path.with_name(f"{path.stem}_frame.png")
    fig, (cam, top) = plt.subplots(1, 2, figsize=(12, 6))
    _draw_camera(cam, f)
    _draw_top(top, frames, i)
    alt = None if f.truth_rel_ned_m is None else -float(f.truth_rel_ned_m[2])
    err = _estimate_error(f)
    fig.suptitle(
        f"{path.name}: frame {i} of {len(frames)}, t = {f.time_s:.1f} s ({why})"
        + ("" if alt is None else f"; altitude {alt:.1f} m")
        + ("" if err is None else f"; estimate {err:.1f} m from the pad"),
        fontsize=10,
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return FrameReport(
        out=str(out),
        time_s=f.time_s,
        frame=i,
        frames=len(frames),
        why=why,
        estimate_error_m=err,
        pad_probability=None if f.perception is None else float(f.perception[2]),
        altitude_m=alt,
    )


def _rgb(c: Any) -> tuple[float, float, float, float]:
    return (c.r, c.g, c.b, c.a)


def _draw_camera(ax, f: LiveFrame) -> None:
    """The frame and the live view's annotations of it, in pixels."""
    from matplotlib.patches import Circle

    from companion.live.messages import decoded, image_annotations

    n_v, n_u = f.image.shape
    ax.imshow(f.image, cmap="gray", vmin=0, vmax=255, extent=(0, n_u, n_v, 0))
    ann = decoded(image_annotations(f))  # what --live serves and log scene writes
    for p in ann.points:  # LineList: segments from point pairs
        pts = [(q.x, q.y) for q in p.points]
        for a, b in zip(pts[0::2], pts[1::2], strict=False):
            ax.plot([a[0], b[0]], [a[1], b[1]], color=_rgb(p.outline_color), lw=p.thickness)
    for c in ann.circles:
        ax.add_patch(
            Circle(
                (c.position.x, c.position.y),
                c.diameter / 2,
                fill=True,
                facecolor=_rgb(c.fill_color),
                edgecolor=_rgb(c.outline_color),
                lw=c.thickness,
            )
        )
    for t in ann.texts:
        ax.text(
            t.position.x,
            t.position.y,
            t.text,
            color=_rgb(t.text_color),
            fontsize=9,
            bbox={"facecolor": "black", "alpha": 0.5, "pad": 1, "lw": 0},
        )
    ax.set_xlim(0, n_u)
    ax.set_ylim(n_v, 0)
    ax.set_title(
        "camera: the CNN's bearing (cross), the estimated pad (blue, 2-sigma)"
        if ann.points or ann.circles
        else "camera (no bearing or estimate logged for this frame)",
        fontsize=9,
    )


def _footprint(f: LiveFrame) -> np.ndarray | None:
    """The image corners' rays from the vehicle to the ground plane (NED, the pad's height)."""
    if f.vehicle_pos_ned_m is None or f.quat_wxyz is None:
        return None
    ground_d = 0.0 if f.pad_pos_ned_m is None else float(f.pad_pos_ned_m[2])
    r = quat_to_rotation(np.asarray(f.quat_wxyz, float))
    t = math.tan(math.radians(CAMERA_FOV_DEG) / 2)
    pos = np.asarray(f.vehicle_pos_ned_m, float)
    corners = []
    for fwd, right in ((t, -t), (t, t), (-t, t), (-t, -t), (t, -t)):
        ray = r @ np.array([fwd, right, 1.0])  # FRD -> NED; the camera looks along body down
        if ray[2] <= 1e-3:
            return None
        corners.append(pos + ray * (ground_d - pos[2]) / ray[2])
    return np.array(corners)


def _draw_top(ax, frames: list[LiveFrame], i: int) -> None:
    """The scene from above (east right, north up) at frame ``i``."""
    from matplotlib.patches import Ellipse, Rectangle

    f = frames[i]
    path = np.array([fr.vehicle_pos_ned_m for fr in frames if fr.vehicle_pos_ned_m is not None])
    if len(path):
        ax.plot(path[:, 1], path[:, 0], color="0.75", lw=1, label="whole flight")
        upto = np.array(
            [fr.vehicle_pos_ned_m for fr in frames[: i + 1] if fr.vehicle_pos_ned_m is not None]
        )
        ax.plot(upto[:, 1], upto[:, 0], color="tab:blue", lw=1.5, label="flown so far")
    pad = np.zeros(3) if f.pad_pos_ned_m is None else np.asarray(f.pad_pos_ned_m, float)
    w, h = f.pad_size_m
    ax.add_patch(
        Rectangle((pad[1] - w / 2, pad[0] - h / 2), w, h, color="tab:green", alpha=0.6, label="pad")
    )
    if f.vehicle_pos_ned_m is not None:
        v = np.asarray(f.vehicle_pos_ned_m, float)
        ax.plot(v[1], v[0], "k^", ms=9, label="vehicle")
        if f.estimate_rel_ned_m is not None:
            est = v - np.asarray(f.estimate_rel_ned_m, float)
            ax.plot(est[1], est[0], "x", color="tab:blue", ms=10, mew=2, label="estimated pad")
            if f.estimate_sigma_m is not None:
                s = np.asarray(f.estimate_sigma_m, float)
                ax.add_patch(
                    Ellipse(
                        (est[1], est[0]), 4 * s[1], 4 * s[0], fill=False, color="tab:blue", ls="--"
                    )
                )
    foot = _footprint(f)
    if foot is not None:
        ax.plot(foot[:, 1], foot[:, 0], color="tab:orange", lw=1, label="camera footprint")
    if f.wind_ned_m_s is not None and float(np.hypot(*f.wind_ned_m_s[:2])) > 0.05:
        speed = float(np.hypot(*f.wind_ned_m_s[:2]))
        north, east = (float(c) / speed for c in f.wind_ned_m_s[:2])
        ax.annotate(  # where the wind blows to, in the axes' corner
            f"wind {speed:.1f} m/s",
            xy=(0.12 + 0.08 * east, 0.88 + 0.08 * north),
            xytext=(0.12, 0.88),
            xycoords="axes fraction",
            arrowprops={"arrowstyle": "->", "color": "tab:purple"},
            color="tab:purple",
            fontsize=8,
        )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("from above", fontsize=9)
    ax.legend(loc="lower right", fontsize=7)
    ax.grid(alpha=0.3)
