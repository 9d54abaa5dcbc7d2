"""``visland log replay FILE --live [HOST:]PORT``: a recorded flight, live in Foxglove.

Any flight log (SITL, rollout or companion) is played back through a
:class:`~companion.live.LiveView` — the same channels a flying process serves — at ``speed``
times its own pace (0: as fast as the client takes it): the frames and events of
:func:`companion.live.replay.logged_frames` (a ``policy`` run again on the logged observations
draws the CNN's bearing and the estimate as they were, or would have been, in the air).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.flightlog import read_log
from companion.live import LiveView, parse_live
from companion.live.replay import REPLAY_TOPICS, LoggedEvent, logged_frames, policy_of

__all__ = ["ReplayConfig", "ReplayReport", "replay_live"]


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


def replay_live(cfg: ReplayConfig, view: LiveView | None = None) -> ReplayReport:
    """Play ``cfg.file`` through a live view (``view``, or one started on ``cfg.live``).

    Raises:
        FlightLogError: the file is not a readable flight log.
        ValueError: a bad ``live`` or ``speed``.
    """
    if not cfg.speed >= 0:
        raise ValueError(f"--speed {cfg.speed}: expected >= 0")
    log = read_log(cfg.file, topics=set(REPLAY_TOPICS))
    policy_name = policy_of(log, cfg.policy)
    policy = None
    if policy_name is not None:
        from companion.policy_net import load_policy

        policy = load_policy(policy_name)
    own = view is None
    if view is None:
        host, port = parse_live(cfg.live)
        view = LiveView(host, port, name=f"visland replay {Path(cfg.file).name}")
    port = view.port
    watched = False
    frames = events = 0
    t_first = t_last = None
    wall0 = time.monotonic()
    try:
        deadline = time.monotonic() + cfg.wait_s
        while cfg.wait_s > 0 and not view.watched and time.monotonic() < deadline:
            time.sleep(0.05)
        start = time.monotonic()
        for item in logged_frames(log, policy):
            t = item.time_s
            t_first = t if t_first is None else t_first
            t_last = t
            if cfg.speed > 0:
                ahead = (t - t_first) / cfg.speed - (time.monotonic() - start)
                if ahead > 0:
                    time.sleep(ahead)
            watched = watched or view.watched
            if isinstance(item, LoggedEvent):
                events += 1
                view.event(t, item.text)
            else:
                frames += 1
                item.stamp_ns = None  # served on the flight's own time, as it flew
                view.publish(item)
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
        sim_s=0.0 if t_first is None else t_last - t_first,
        wall_s=time.monotonic() - wall0,
    )
