"""What a source knows at one frame (:class:`LiveFrame`), the companion's (:func:`live_frame`),
and ``--live``'s argument (:func:`parse_live`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.contract import Command, GroundTruth, Observation
from companion.contract.messages import quat_from_euler
from companion.contract.records import PolicyEstimateRecord

__all__ = [
    "DEFAULT_LIVE_PORT",
    "LiveFrame",
    "live_frame",
    "pad_extent_m",
    "parse_live",
    "with_truth",
]

DEFAULT_LIVE_PORT = 8765
"""Foxglove's default WebSocket port."""

PAPER_PAD_EXTENT_M = (4.0, 4.0)
"""The paper's pad (along its forward axis, across it): the extent where no other was drawn."""


def parse_live(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` -> ``(host, port)``; the host defaults to 127.0.0.1 (this machine only).

    Raises:
        ValueError: not a port in 1..65535 (names what was given).
    """
    host, _, port = text.rpartition(":")
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 < number < 65536:
        raise ValueError(f"--live {text!r}: expected [HOST:]PORT with a port in 1..65535")
    return host or "127.0.0.1", number


@dataclass
class LiveFrame:
    """What a source knows at one camera frame (None: it does not know it).

    Attributes:
        time_s: the frame's time (sim time for the SITL and logs; the autopilot's for the
            companion's SITL camera).
        image: (128, 128) uint8.
        vehicle_pos_ned_m: the vehicle in ``ned`` (the companion: its estimate).
        quat_wxyz: the vehicle's attitude (body FRD -> NED).
        pad_pos_ned_m, pad_quat_wxyz: the pad's surface centre and attitude (None: still, level
            at the origin); ``pad_size_m`` its extent.
        perception: the CNN's (tan_right, tan_forward, pad probability).
        estimate_rel_ned_m, estimate_sigma_m: the estimator's vehicle-relative-to-pad position
            and its 1-sigma per axis.
        truth_rel_ned_m: the true vehicle-relative-to-pad position (SITL and logs only).
        command: (thrust_norm, p, q, r) flown.
        range_m: the radar's reading; wind_ned_m_s: the wind (simulation only).
        state: the flight's state or the autopilot's mode; link: link counters.
        stamp_ns: the messages' stamp when it is not ``time_s`` (a log's frame: its image's
            own stamp, on the file's clock, so the annotations match the logged image exactly).
    """

    time_s: float
    image: np.ndarray | None = None
    vehicle_pos_ned_m: np.ndarray | None = None
    quat_wxyz: np.ndarray | None = None
    pad_pos_ned_m: np.ndarray | None = None
    pad_quat_wxyz: np.ndarray | None = None
    pad_size_m: tuple[float, float] = PAPER_PAD_EXTENT_M
    perception: tuple[float, float, float] | None = None
    estimate_rel_ned_m: np.ndarray | None = None
    estimate_sigma_m: np.ndarray | None = None
    truth_rel_ned_m: np.ndarray | None = None
    command: tuple[float, float, float, float] | None = None
    range_m: float | None = None
    wind_ned_m_s: np.ndarray | None = None
    state: str | None = None
    link: dict[str, int] = field(default_factory=dict)
    stamp_ns: int | None = None


def pad_extent_m(drawn_pad: Mapping[str, Any] | None) -> tuple[float, float]:
    """A :class:`LiveFrame`'s ``pad_size_m`` (along the pad's forward axis, across it) from the
    pad an episode drew (its world record's ``pad``: ``size_m`` = [width, height] as the pad's
    image lies, north up); the paper's 4 m pad where none was drawn."""
    if not drawn_pad or "size_m" not in drawn_pad:
        return PAPER_PAD_EXTENT_M
    width, height = (float(v) for v in drawn_pad["size_m"])
    return (height, width)


def live_frame(
    obs: Observation,
    truth: GroundTruth | None,
    policy_state: Any,
    command: Command | None,
    state: str | None = None,
    link: Any = None,
) -> LiveFrame:
    """The companion's frame: what it saw (the image, the CNN's bearing), what it believes (the
    estimator's pad) and flew; with a SITL's ODOMETRY (``truth``) the scene is the true world
    and the estimate is drawn against it, else the pad-centred world of the estimate itself."""
    # the CNN's bearing and pad probability, the estimator's pad: as /policy/estimate logs them
    est = PolicyEstimateRecord.from_state(policy_state, obs.frame_id)
    perception = rel = sigma = None
    if est is not None and est.pad_probability is not None:
        perception = (est.tan_right, est.tan_forward, est.pad_probability)
    if est is not None and est.rel_pos_ned_m is not None:
        rel = np.asarray(est.rel_pos_ned_m, float)
        sigma = np.asarray(est.sigma_ned_m, float)
    quat = quat_from_euler(*(float(a) for a in obs.attitude_rad))
    frame = LiveFrame(
        time_s=float(obs.image_time_s),
        image=obs.image,
        quat_wxyz=quat,
        perception=perception,
        estimate_rel_ned_m=rel,
        estimate_sigma_m=sigma,
        vehicle_pos_ned_m=rel,
        command=None
        if command is None
        else (command.thrust_norm, *(float(v) for v in command.rate_frd_rad_s)),
        range_m=_float(obs.range_m),
        state=state,
        link={}
        if link is None
        else {k: int(v) for k, v in vars(link).items() if isinstance(v, int)},
    )
    if truth is not None:
        with_truth(frame, truth)
    return frame


def with_truth(frame: LiveFrame, truth: GroundTruth) -> LiveFrame:
    """``frame`` placed in the true world: the vehicle, the pad, the vehicle relative to the
    pad and the wind of ``truth`` (the attitude stays the frame's)."""
    frame.vehicle_pos_ned_m = np.asarray(truth.pos_ned_m, float)
    frame.pad_pos_ned_m = truth.pad_pos_ned_m
    frame.pad_quat_wxyz = truth.pad_quat_wxyz
    frame.truth_rel_ned_m = np.asarray(truth.pad_relative[0], float)
    frame.wind_ned_m_s = truth.wind_ned_m_s
    return frame


def _float(v: Any) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)
