"""A recorded flight as the live view's frames: :func:`logged_frames`.

Any flight log (SITL, rollout or companion) is read back as what a flying process would have
published: one :class:`~companion.live.LiveFrame` per camera frame, with the newest ground truth
(vehicle, pad, wind), observation (attitude, radar range) and command logged before it, and the
``/events`` between them. ``visland log replay`` serves them live; :mod:`companion.live.scene_log`
writes them into the log itself.

With a ``policy`` (a vision checkpoint; a companion log of one names it itself) the policy is run
again on the logged observations, as ``visland companion --replay`` does: the CNN's bearing and
the estimator's pad are drawn as they were in the air — for a SITL or in-process log, where only
the truth was recorded, what the model *would* have seen and believed there. Without one, an
in-process flight's own ``/policy/estimate`` is drawn (no policy run).
"""

from __future__ import annotations

import base64
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.contract import GroundTruth
from companion.contract.companion_records import CompanionObservationRecord
from companion.contract.messages import quat_from_euler
from companion.contract.records import (
    TIME_S,
    GroundTruthRecord,
    ObservationRecord,
    RawImageRecord,
)
from companion.contract.topics import (
    TOPIC_COMMAND,
    TOPIC_COMPANION_COMMAND,
    TOPIC_COMPANION_OBSERVATION,
    TOPIC_EVENTS,
    TOPIC_GROUNDTRUTH,
    TOPIC_IMAGE,
    TOPIC_OBSERVATION,
    TOPIC_POLICY_ESTIMATE,
)
from companion.flightlog import FlightLog
from companion.live.frame import LiveFrame, live_frame, pad_extent_m, with_truth
from companion.policy_net.guard import PadNotFound

__all__ = ["REPLAY_TOPICS", "LoggedEvent", "logged_frames", "policy_of"]

REPLAY_TOPICS = (
    TOPIC_IMAGE,
    TOPIC_GROUNDTRUTH,
    TOPIC_OBSERVATION,
    TOPIC_COMPANION_OBSERVATION,
    TOPIC_COMMAND,
    TOPIC_COMPANION_COMMAND,
    TOPIC_POLICY_ESTIMATE,
    TOPIC_EVENTS,
)
"""The topics a replay reads (``read_log(path, topics=REPLAY_TOPICS)``)."""


@dataclass(frozen=True)
class LoggedEvent:
    """One ``/events`` record: its time and ``"kind: text"``."""

    time_s: float
    text: str


def policy_of(log: FlightLog, given: str | None) -> str | None:
    """The checkpoint to run again: ``given``, else the one a companion log names if it is a
    file here, else None."""
    if given is not None:
        return given
    name = (log.metadata.get("policy") or {}).get("name")
    return name if name and Path(name).is_file() else None


def logged_frames(log: FlightLog, policy: Any = None) -> Iterator[LiveFrame | LoggedEvent]:
    """The flight in ``log`` (read with at least :data:`REPLAY_TOPICS`) in time order: a
    :class:`LiveFrame` per camera frame (``stamp_ns``: the image's own stamp) and a
    :class:`LoggedEvent` per event. ``policy`` (a loaded policy, or None) is run again on the
    logged observations, up to where its landing guard gives up (a ``pad_not_found`` flight
    ends there too)."""
    state = None if policy is None else policy.initial_state()
    # by time; at one time the image last, so its frame has the readings stamped with it
    rank = {topic: (1 if topic == TOPIC_IMAGE else 0) for topic in REPLAY_TOPICS}
    stream = sorted(
        (
            (float(m.get(TIME_S, 0.0)), topic, m)
            for topic in REPLAY_TOPICS
            for m in log.topic(topic)
        ),
        key=lambda item: (item[0], rank[item[1]]),
    )
    pad_size = pad_extent_m((log.metadata.get("episode") or {}).get("pad"))
    truth: GroundTruth | None = None
    obs_rec: Any = None
    command = None
    estimate: dict[str, Any] | None = None
    for t, topic, msg in stream:
        if topic == TOPIC_GROUNDTRUTH:
            truth = GroundTruthRecord.from_dict(msg).groundtruth(msg[TIME_S])
        elif topic == TOPIC_OBSERVATION:
            obs_rec = ObservationRecord.from_dict(msg)
        elif topic == TOPIC_COMPANION_OBSERVATION:
            obs_rec = CompanionObservationRecord.from_dict(msg)
        elif topic in (TOPIC_COMMAND, TOPIC_COMPANION_COMMAND):
            command = _command(msg)
        elif topic == TOPIC_POLICY_ESTIMATE:
            estimate = msg
        elif topic == TOPIC_EVENTS:
            yield LoggedEvent(t, f"{msg.get('kind')}: {msg.get('text')}")
        elif topic == TOPIC_IMAGE:
            rec = RawImageRecord.from_dict(msg)
            image = np.frombuffer(base64.b64decode(rec.data), dtype=np.uint8)
            image = image.reshape(rec.height, rec.width)
            frame = _frame(t, image, truth, obs_rec, command, estimate)
            if policy is not None and obs_rec is not None:
                obs = _observation(obs_rec, image)
                try:
                    _, state = policy.act(obs, None, state)
                except PadNotFound:  # the guard gave up here, as the flight did: the rest
                    policy = None  # of the log is drawn as it was logged
                else:
                    frame = live_frame(obs, truth, state, None)
                    frame.command = command
                    frame.time_s = t
            frame.pad_size_m = pad_size
            frame.stamp_ns = rec.timestamp.sec * 1_000_000_000 + rec.timestamp.nsec
            yield frame


def _command(msg: dict[str, Any]) -> tuple[float, float, float, float]:
    rates = msg["rate_frd_rad_s"]
    return (float(msg["thrust_norm"]), *(float(r) for r in rates))


def _observation(rec: Any, image: np.ndarray) -> Any:
    if isinstance(rec, ObservationRecord):
        return rec.observation(image)
    keep = set(ObservationRecord.field_names())
    values = {
        k: v
        for k, v in rec.to_dict().items()
        if k in keep and not (k == "hover_thrust_norm" and v is None)  # null: not reported
    }
    return ObservationRecord.from_dict(values).observation(image)


def _frame(
    t: float,
    image: np.ndarray,
    truth: GroundTruth | None,
    obs_rec: Any,
    command: Any,
    estimate: dict[str, Any] | None = None,
) -> LiveFrame:
    """A frame from the logged truth, observation, command and (an in-process flight of a
    learned policy) the policy's logged estimate — no policy run."""
    frame = LiveFrame(time_s=t, image=image, command=command)
    if estimate is not None:
        if estimate.get("pad_probability") is not None:
            frame.perception = (
                float(estimate["tan_right"]),
                float(estimate["tan_forward"]),
                float(estimate["pad_probability"]),
            )
        if estimate.get("rel_pos_ned_m") is not None:
            frame.estimate_rel_ned_m = np.asarray(estimate["rel_pos_ned_m"], float)
            frame.estimate_sigma_m = np.asarray(estimate["sigma_ned_m"], float)
    if obs_rec is not None:
        frame.quat_wxyz = quat_from_euler(*(float(a) for a in obs_rec.attitude_rad))
        frame.range_m = None if obs_rec.range_m is None else float(obs_rec.range_m)
    if truth is not None:
        with_truth(frame, truth).quat_wxyz = truth.quat_wxyz
    return frame
