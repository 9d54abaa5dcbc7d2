"""``visland log info``: what is in an MCAP flight log, and where each plot panel reads from.

Works on the three kinds of flight log (DESIGN.md "Flight logs"), telling them apart by topic:

* **sitl** — ``visland sitl``: ``/groundtruth/state`` at every frame, ``/autopilot/command`` (the
  command the autopilot applied, whatever the mode), ``/mavlink/in|out/<NAME>``;
* **rollout** — the in-process path (``visland collect``/``eval``): ``/groundtruth/state``,
  ``/observation``, ``/command`` per control step;
* **companion** — the on-board record (``companion.record``): ``/companion/observation``,
  ``/companion/command``, ``/mavlink/in/<NAME>`` as received (ODOMETRY = ground truth only for
  privileged flights), ``/companion/summary``; no ground-truth channel.

Each plot panel (:mod:`tools.log_plots`) takes the best source the log has (ground truth before
measurements, the pilot's command before the autopilot's before the raw SET_ATTITUDE_TARGET;
:data:`SOURCES`) and says which it used in its title; a panel with no source says what is
missing instead of drawing nothing.
Logs are read with :func:`companion.flightlog.read_log`, so a truncated (crashed) log shows its
readable prefix and is reported as truncated.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from companion.contract.companion_records import (
    CompanionCommandRecord,
    CompanionObservationRecord,
    CompanionSummaryRecord,
)
from companion.contract.record_base import RecordError
from companion.contract.records import (
    AutopilotCommandRecord,
    CommandRecord,
    EpisodeResultRecord,
    GroundTruthRecord,
    ObservationRecord,
)
from companion.contract.topics import (
    TOPIC_AUTOPILOT_COMMAND,
    TOPIC_COMMAND,
    TOPIC_COMPANION_COMMAND,
    TOPIC_COMPANION_OBSERVATION,
    TOPIC_COMPANION_PREFIX,
    TOPIC_COMPANION_SUMMARY,
    TOPIC_GROUNDTRUTH,
    TOPIC_MAVLINK_IN,
    TOPIC_MAVLINK_OUT,
    TOPIC_OBSERVATION,
    TOPIC_RESULT,
)
from companion.flightlog import FlightLog, read_log
from sitl_sim.physics.dynamics import euler_from_quat

__all__ = [
    "PANELS",
    "PANEL_WIDTH",
    "RESULT_TOPICS",
    "SOURCES",
    "PlotSources",
    "fmt_value",
    "format_info",
    "last_result",
    "log_info",
    "log_kind",
    "plot_sources",
    "result_record",
    "verdict",
]


PANELS = ("position", "altitude", "attitude", "command")
"""The plot's panels: top view, altitude vs time, attitude vs time, commands vs time."""

_UINT16_MAX = 65_535

Getter = Callable[[dict[str, Any]], Any]
R = TypeVar("R")


def _radar_cm(m: dict[str, Any]) -> float | None:
    """DISTANCE_SENSOR in m; UINT16_MAX = no return."""
    return None if m["current_distance"] >= _UINT16_MAX else m["current_distance"] / 100


def _euler(quat_wxyz: Any) -> np.ndarray:
    return euler_from_quat(np.asarray(quat_wxyz, dtype=float))


def _record(record: type[R], get: Callable[[R], Any]) -> Getter:
    """A getter that reads a message as its contract ``record`` (MAVLink messages are read by
    the dialect's own field names)."""
    return lambda m: get(record.from_dict(m))


def _command(r: Any) -> tuple[float, ...]:
    """thrust_norm, p, q, r of any command record."""
    return (r.thrust_norm, *r.rate_frd_rad_s)


SOURCES: dict[str, tuple[tuple[str, Getter, str], ...]] = {
    "position": (  # NED metres
        (TOPIC_GROUNDTRUTH, _record(GroundTruthRecord, lambda r: r.pos_ned_m), "ground truth"),
        (
            TOPIC_MAVLINK_IN + "ODOMETRY",
            lambda m: (m["x"], m["y"], m["z"]),
            "ODOMETRY (ground truth)",
        ),
    ),
    "altitude": (  # metres above ground (ground truth) or radar range
        (
            TOPIC_GROUNDTRUTH,
            _record(GroundTruthRecord, lambda r: -r.pos_ned_m[2]),
            "altitude (ground truth)",
        ),
        (TOPIC_MAVLINK_IN + "ODOMETRY", lambda m: -m["z"], "altitude (ODOMETRY)"),
        (
            TOPIC_OBSERVATION,
            _record(ObservationRecord, lambda r: r.range_m),
            "radar range (observation)",
        ),
        (
            TOPIC_COMPANION_OBSERVATION,
            _record(CompanionObservationRecord, lambda r: r.range_m),
            "radar range (observation)",
        ),
        (TOPIC_MAVLINK_OUT + "DISTANCE_SENSOR", _radar_cm, "radar range (DISTANCE_SENSOR)"),
        (TOPIC_MAVLINK_IN + "DISTANCE_SENSOR", _radar_cm, "radar range (DISTANCE_SENSOR)"),
    ),
    "attitude": (  # roll, pitch, yaw (rad)
        (
            TOPIC_GROUNDTRUTH,
            _record(GroundTruthRecord, lambda r: _euler(r.quat_wxyz)),
            "ground truth",
        ),
        (TOPIC_OBSERVATION, _record(ObservationRecord, lambda r: r.attitude_rad), "observation"),
        (
            TOPIC_COMPANION_OBSERVATION,
            _record(CompanionObservationRecord, lambda r: r.attitude_rad),
            "observation",
        ),
        (TOPIC_MAVLINK_OUT + "ATTITUDE", lambda m: (m["roll"], m["pitch"], m["yaw"]), "ATTITUDE"),
        (TOPIC_MAVLINK_IN + "ATTITUDE", lambda m: (m["roll"], m["pitch"], m["yaw"]), "ATTITUDE"),
    ),
    "command": (  # thrust_norm, p, q, r
        (TOPIC_COMMAND, _record(CommandRecord, _command), "pilot"),
        (TOPIC_COMPANION_COMMAND, _record(CompanionCommandRecord, _command), "pilot"),
        (TOPIC_AUTOPILOT_COMMAND, _record(AutopilotCommandRecord, _command), "autopilot"),
        (
            TOPIC_MAVLINK_IN + "SET_ATTITUDE_TARGET",
            lambda m: (m["thrust"], m["body_roll_rate"], m["body_pitch_rate"], m["body_yaw_rate"]),
            "SET_ATTITUDE_TARGET",
        ),
    ),
}
"""Per panel, the topics it can draw, best first: ``(topic, message -> values, label)``."""

PANEL_WIDTH = {"position": 3, "altitude": 1, "attitude": 3, "command": 4}
RESULT_TOPICS = (TOPIC_RESULT, TOPIC_COMPANION_SUMMARY)


@dataclass(frozen=True)
class PlotSources:
    """Which topic feeds each panel (None: the log has none of the topics it could use).

    Attributes:
        sources: panel name (:data:`PANELS`) -> topic or None.
        missing: one line per panel without a source, naming the topics it looked for.
    """

    sources: dict[str, str | None]
    missing: list[str] = field(default_factory=list)


def log_kind(topics: set[str]) -> str:
    if any(t.startswith(TOPIC_COMPANION_PREFIX) for t in topics):
        return "companion"
    if TOPIC_AUTOPILOT_COMMAND in topics or any(t.startswith(TOPIC_MAVLINK_OUT) for t in topics):
        return "sitl"
    if TOPIC_GROUNDTRUTH in topics:
        return "rollout"
    if TOPIC_OBSERVATION in topics or TOPIC_COMMAND in topics:
        return "companion"
    return "unknown"


def plot_sources(log: FlightLog) -> PlotSources:
    """The topic each plot panel will draw from, and what is missing."""
    sources: dict[str, str | None] = {}
    missing: list[str] = []
    for panel in PANELS:
        topics = list(dict.fromkeys(topic for topic, _, _ in SOURCES[panel]))
        found = next((t for t in topics if log.topic(t)), None)
        sources[panel] = found
        if found is None:
            missing.append(f"{panel}: none of {', '.join(topics)} in the log")
    return PlotSources(sources, missing)


def log_info(path: str | Path) -> dict[str, Any]:
    """A summary of one flight log (JSON-ready).

    Keys: ``path``, ``size_bytes``, ``kind`` (sitl | rollout | companion | unknown),
    ``truncated`` and ``error`` (why reading stopped early), ``messages`` (total),
    ``start_time_s`` / ``end_time_s`` / ``duration_s`` (the log's sim clock), ``topics``
    (topic -> ``{count, schema}``, every channel of the readable part), ``metadata`` (record
    name -> its keys), ``episode`` (the ``episode`` metadata record, if any), ``result`` (the
    last ``/episode/result``, else the companion's ``/companion/summary``, else None),
    ``plot_sources`` and ``plot_missing``.

    Raises:
        FlightLogError: the file is missing or not an MCAP file.
    """
    path = Path(path)
    log = read_log(path)
    times = [m["time_s"] for msgs in log.messages.values() for m in msgs if "time_s" in m]
    topics = {
        topic: {
            "count": len(log.topic(topic)) or log.binary.get(topic, 0),
            "schema": log.schemas.get(topic, ""),
        }
        for topic in sorted(set(log.schemas) | set(log.messages))
    }
    sources = plot_sources(log)
    return {
        "path": str(path),
        "size_bytes": path.stat().st_size,
        "kind": log_kind(set(topics)),
        "truncated": log.truncated,
        "error": log.error,
        "messages": sum(v["count"] for v in topics.values()),
        "start_time_s": min(times) if times else None,
        "end_time_s": max(times) if times else None,
        "duration_s": log.duration_s,
        "topics": topics,
        "metadata": {name: sorted(values) for name, values in log.metadata.items()},
        "episode": log.metadata.get("episode"),
        "result": last_result(log),
        "plot_sources": sources.sources,
        "plot_missing": sources.missing,
    }


def format_info(info: dict[str, Any]) -> str:
    """``log_info``'s dict as the text ``visland log info`` prints."""
    state = f"TRUNCATED: {info['error']}" if info["truncated"] else "complete (footer read)"
    lines = [
        f"{info['path']}  ({info['size_bytes'] / 1024:.0f} KiB, {info['kind']} log)",
        f"  {state}",
    ]
    if info["start_time_s"] is not None:
        lines.append(
            f"  time {info['start_time_s']:.3f} .. {info['end_time_s']:.3f} s "
            f"(duration {info['duration_s']:.3f} s), {info['messages']} messages"
        )
    width = max((len(t) for t in info["topics"]), default=0)
    lines.append("  topics:")
    for topic, row in info["topics"].items():
        lines.append(f"    {topic:<{width}}  {row['count']:>7}  {row['schema']}")
    lines.append("  metadata:")
    for name, keys in info["metadata"].items():
        lines.append(f"    {name}: {', '.join(keys)}")
    if not info["metadata"]:
        lines.append("    (none)")
    result = result_record(info["result"])
    if result is None:
        lines.append("  result: none (no /episode/result)")
    elif isinstance(result, CompanionSummaryRecord):
        reason = result.reason or "no reason given"
        lines.append(f"  result (companion summary): {result.result} ({reason})")
    else:
        shown = ("landed", "success", "landing_error_m", "touchdown_vertical_speed_m_s", "tilt_deg")
        parts = [f"{k} {fmt_value(getattr(result, k))}" for k in shown]
        if result.aborted is True:
            parts.insert(0, "ABORTED")
        lines.append(f"  result: {', '.join(parts)}")
    for line in info["plot_missing"]:
        lines.append(f"  plot: no {line}")
    return "\n".join(lines)


def fmt_value(value: Any, spec: str = ".3f") -> str:
    """``value`` for a table, caption or summary line: a number by ``spec``; ``n/a`` for None,
    NaN and inf (not defined, e.g. no touchdown); anything else (a bool: landed) as ``str``."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    number = isinstance(value, int | float) and not isinstance(value, bool)
    return format(value, spec) if number else str(value)


def last_result(log: FlightLog) -> dict[str, Any] | None:
    """The episode's ``/episode/result``, else the companion's ``/companion/summary`` (the
    message as logged)."""
    for topic in RESULT_TOPICS:
        msgs = log.topic(topic)
        if msgs:
            return msgs[-1]
    return None


Result = EpisodeResultRecord | CompanionSummaryRecord


def result_record(message: dict[str, Any] | None) -> Result | None:
    """:func:`last_result`'s message as its record (None: no result, or one that is not a
    whole record, e.g. from a truncated or foreign log)."""
    if message is None:
        return None
    record = CompanionSummaryRecord if isinstance(message.get("result"), str) else None
    try:
        return (record or EpisodeResultRecord).from_dict(message)
    except (RecordError, TypeError):
        return None


def verdict(r: EpisodeResultRecord) -> str:
    """One word or phrase for an ``/episode/result``."""
    if r.aborted is True:
        return "aborted"
    if not r.landed:
        return "timeout"
    return "success" if r.success else "landed, not a success"
