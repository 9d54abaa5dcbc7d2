"""``visland log replay FILE --live [HOST:]PORT``: a recorded flight, live in Foxglove.

Any flight log (SITL, rollout or companion) is played back through a
:class:`~companion.live.LiveView` — the same channels a flying process serves — at ``speed``
times its own pace (0: as fast as the client takes it). Each camera frame becomes a
:class:`~companion.live.LiveFrame` with the newest ground truth (vehicle, pad, wind), observation
(attitude, radar range) and command logged before it; ``/events`` go out as they come.

With ``policy`` (a vision checkpoint; a companion log of one names it itself) the policy is
run again on the logged observations, as ``visland companion --replay`` does: the CNN's bearing
and the estimator's pad are drawn as they were in the air — for a SITL or in-process log, where
only the truth was recorded, what the model *would* have seen and believed there.
"""

from __future__ import annotations

import base64
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.contract import GroundTruth
from companion.contract.companion_records import CompanionObservationRecord
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
from companion.flightlog import read_log
from companion.live import LiveFrame, LiveView, live_frame, parse_live, with_truth

__all__ = ["ReplayConfig", "ReplayReport", "replay_live"]

_TOPICS = (
    TOPIC_IMAGE,
    TOPIC_GROUNDTRUTH,
    TOPIC_OBSERVATION,
    TOPIC_COMPANION_OBSERVATION,
    TOPIC_COMMAND,
    TOPIC_COMPANION_COMMAND,
    TOPIC_POLICY_ESTIMATE,
    TOPIC_EVENTS,
)


@dataclass(frozen=True)
class ReplayConfig:
    file: Path
    live: str = "8765"
    """``[HOST:]PORT`` to serve on."""
    speed: float = 1.0
    """Times the flight's own pace (0: no pauses)."""
    policy: str | None = None
    """A vision checkpoint run again on the logged observations (None: a companion log's own,
    else none)."""
    wait_s: float = 10.0
    """Wait this long for a client to subscribe before playing (0: play at once)."""


@dataclass(frozen=True)
class ReplayReport:
    file: str
    port: int
    frames: int
    events: int
    watched: bool
    """A client subscribed at some point."""
    policy: str | None
    sim_s: float
    wall_s: float

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _image(msg: dict[str, Any]) -> np.ndarray:
    rec = RawImageRecord.from_dict(msg)
    data = np.frombuffer(base64.b64decode(rec.data), dtype=np.uint8)
    return data.reshape(rec.height, rec.width)


def _command(msg: dict[str, Any]) -> tuple[float, float, float, float]:
    rates = msg["rate_frd_rad_s"]
    return (float(msg["thrust_norm"]), *(float(r) for r in rates))


def _policy_of(log: Any, given: str | None) -> str | None:
    if given is not None:
        return given
    name = (log.metadata.get("policy") or {}).get("name")
    return name if name and Path(name).is_file() else None


def replay_live(cfg: ReplayConfig, view: LiveView | None = None) -> ReplayReport:
    """Play ``cfg.file`` through a live view (``view``, or one started on ``cfg.live``).

    Raises:
        FlightLogError: the file is not a readable flight log.
        ValueError: a bad ``live`` or ``speed``.
    """
    if not cfg.speed >= 0:
        raise ValueError(f"--speed {cfg.speed}: expected >= 0")
    log = read_log(cfg.file, topics=set(_TOPICS))
    policy_name = _policy_of(log, cfg.policy)
    policy = state = None
    if policy_name is not None:
        from companion.policy_net import load_policy

        policy = load_policy(policy_name)
        state = policy.initial_state()
    # by time; at one time the image last, so its frame has the readings stamped with it
    rank = {topic: (1 if topic == TOPIC_IMAGE else 0) for topic in _TOPICS}
    stream = sorted(
        ((float(m.get(TIME_S, 0.0)), topic, m) for topic in _TOPICS for m in log.topic(topic)),
        key=lambda item: (item[0], rank[item[1]]),
    )
    own = view is None
    if view is None:
        host, port = parse_live(cfg.live)
        view = LiveView(host, port, name=f"visland replay {Path(cfg.file).name}")
    port = view.port
    watched = False
    frames = events = 0
    wall0 = time.monotonic()
    try:
        deadline = time.monotonic() + cfg.wait_s
        while cfg.wait_s > 0 and not view.watched and time.monotonic() < deadline:
            time.sleep(0.05)
        truth: GroundTruth | None = None
        obs_rec: Any = None
        command = None
        estimate: dict[str, Any] | None = None
        t_first = stream[0][0] if stream else 0.0
        start = time.monotonic()
        for t, topic, msg in stream:
            if cfg.speed > 0:
                ahead = (t - t_first) / cfg.speed - (time.monotonic() - start)
                if ahead > 0:
                    time.sleep(ahead)
            watched = watched or view.watched
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
                events += 1
                view.event(t, f"{msg.get('kind')}: {msg.get('text')}")
            elif topic == TOPIC_IMAGE:
                frames += 1
                image = _image(msg)
                frame = _frame(t, image, truth, obs_rec, command, estimate)
                if policy is not None and obs_rec is not None:
                    obs = _observation(obs_rec, image)
                    _, state = policy.act(obs, None, state)
                    frame = live_frame(obs, truth, state, None)
                    frame.command = command
                view.publish(frame)
    finally:
        if own:
            view.close()
    return ReplayReport(
        file=str(cfg.file),
        port=port,
        frames=frames,
        events=events,
        watched=watched,
        policy=policy_name,
        sim_s=(stream[-1][0] - stream[0][0]) if stream else 0.0,
        wall_s=time.monotonic() - wall0,
    )


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
    from companion.live.frame import quat_from_euler

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
