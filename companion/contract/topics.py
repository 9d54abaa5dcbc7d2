"""Every flight-log topic name and its schema name, in one place.

Three kinds of MCAP flight log exist (DESIGN.md "Flight logs"); they share topic names where the
record means the same thing, so one reader serves all three:

* the **rollout** log an in-process flight writes (``sitl_sim.flight_record``): per control step
  ``/camera/image``, ``/observation``, ``/groundtruth/state`` + ``/groundtruth/pose``,
  ``/command``; ``/episode/scenario`` first, ``/episode/result`` last;
* the **SITL** log (``visland sitl``): the rollout topics (so it is a training record too) plus
  ``/autopilot/command``, ``/mavlink/in/<NAME>``, ``/mavlink/out/<NAME>``, ``/mavlink/rx_errors``,
  ``/mavlink/link_stats`` and ``/events``;
* the **companion** log (``visland companion``): ``/mavlink/in/<NAME>``, ``/camera/image``,
  ``/companion/observation``, ``/companion/command``, ``/events``, ``/companion/summary``.

``visland relabel`` writes ``/label/command`` into a sibling labels file. Schemas are JSON +
jsonschema whose title is the schema name, Foxglove's where one fits (``foxglove.RawImage``,
``foxglove.PoseInFrame``); a MAVLink message ``NAME`` is logged as schema ``mavlink.NAME``.
Topic strings are never retyped elsewhere: import them from here. Each schema's fields are its
record in :mod:`companion.contract.records` (``RECORDS``: schema name -> record).
"""

from __future__ import annotations

__all__ = [
    "LOG_KIND_TOPICS",
    "SCHEMAS",
    "SCHEMA_AUTOPILOT_COMMAND",
    "SCHEMA_COMMAND",
    "SCHEMA_COMPANION_COMMAND",
    "SCHEMA_COMPANION_LANDING_TARGET",
    "SCHEMA_COMPANION_OBSERVATION",
    "SCHEMA_COMPANION_SUMMARY",
    "SCHEMA_EPISODE_RESULT",
    "SCHEMA_EPISODE_SCENARIO",
    "SCHEMA_EVENT",
    "SCHEMA_GROUNDTRUTH",
    "SCHEMA_GROUNDTRUTH_POSE",
    "SCHEMA_IMAGE",
    "SCHEMA_LABEL",
    "SCHEMA_LINK_STATS",
    "SCHEMA_OBSERVATION",
    "SCHEMA_POLICY_ESTIMATE",
    "SCHEMA_PRECLAND",
    "SCHEMA_RX_ERROR",
    "TOPIC_AUTOPILOT_COMMAND",
    "TOPIC_COMMAND",
    "TOPIC_COMPANION_COMMAND",
    "TOPIC_COMPANION_LANDING_TARGET",
    "TOPIC_COMPANION_OBSERVATION",
    "TOPIC_COMPANION_PREFIX",
    "TOPIC_COMPANION_SUMMARY",
    "TOPIC_EVENTS",
    "TOPIC_GROUNDTRUTH",
    "TOPIC_GROUNDTRUTH_POSE",
    "TOPIC_IMAGE",
    "TOPIC_LABEL",
    "TOPIC_LINK_STATS",
    "TOPIC_MAVLINK_IN",
    "TOPIC_MAVLINK_OUT",
    "TOPIC_OBSERVATION",
    "TOPIC_POLICY_ESTIMATE",
    "TOPIC_PRECLAND",
    "TOPIC_RESULT",
    "TOPIC_RX_ERRORS",
    "TOPIC_SCENARIO",
    "mavlink_schema",
]

# ------------------------------------------------------------------ shared by every log kind
TOPIC_IMAGE = "/camera/image"
"""Camera frames (``foxglove.RawImage`` mono8, base64 ``data``), every frame rendered/received."""
TOPIC_EVENTS = "/events"
"""State-machine transitions, link events, failsafes (``kind``, ``text``)."""

# -------------------------------------------------------------- rollout + SITL (training record)
TOPIC_OBSERVATION = "/observation"
"""The Observation a policy saw at a control step (image excluded: see the frame)."""
TOPIC_GROUNDTRUTH = "/groundtruth/state"
"""The privileged GroundTruth at each frame (never read by a deployable policy)."""
TOPIC_GROUNDTRUTH_POSE = "/groundtruth/pose"
"""The same pose as ``foxglove.PoseInFrame`` for Foxglove's 3D panel."""
TOPIC_COMMAND = "/command"
"""The Command flown for the period after a frame, keyed by ``frame_id``."""
TOPIC_POLICY_ESTIMATE = "/policy/estimate"
"""A learned policy's belief after a frame (in-process flights): the CNN's bearing and pad
probability, the pad estimator's relative position, velocity and 1-sigma."""
TOPIC_SCENARIO = "/episode/scenario"
"""The episode's initial state and seed, first in the file."""
TOPIC_RESULT = "/episode/result"
"""The episode's result (``sitl_sim.metrics.EpisodeResult``), last in the file."""

# ------------------------------------------------------------------ SITL only
TOPIC_AUTOPILOT_COMMAND = "/autopilot/command"
"""The command the autopilot applied for each control period (any mode)."""
TOPIC_MAVLINK_IN = "/mavlink/in/"
"""Prefix: ``/mavlink/in/<NAME>`` is every message received (both the SITL and the companion)."""
TOPIC_MAVLINK_OUT = "/mavlink/out/"
"""Prefix: ``/mavlink/out/<NAME>`` is every message the SITL sent."""
TOPIC_RX_ERRORS = "/mavlink/rx_errors"
"""Datagrams the SITL's endpoints refused, with the reason."""
TOPIC_LINK_STATS = "/mavlink/link_stats"
"""The SITL's per-link counters, when they change."""

# ------------------------------------------------------------------ companion only
TOPIC_COMPANION_PREFIX = "/companion/"
"""Prefix of the topics only the companion writes (tells a companion log apart)."""
TOPIC_COMPANION_OBSERVATION = "/companion/observation"
"""The observation the companion's policy saw (image excluded)."""
TOPIC_COMPANION_COMMAND = "/companion/command"
"""Every command computed: raw, clamped, ``sent``, latency."""
TOPIC_COMPANION_SUMMARY = "/companion/summary"
"""The flight's counters, last."""
TOPIC_COMPANION_LANDING_TARGET = "/companion/landing_target"
"""Landing-target mode: each frame's pad estimate and the LANDING_TARGET sent (or why not)."""
TOPIC_PRECLAND = "/autopilot/precland"
"""SITL, AUTO.PRECLAND: each control period's precision-land state, the autopilot's own
estimate and its landing-target estimate (what the precision land flew on)."""

# ------------------------------------------------------------- labels (relabel's sibling file)
TOPIC_LABEL = "/label/command"
"""The expert's Command for each ``frame_id`` of a log, and the recorded one beside it."""

# ------------------------------------------------------------------ schema names
SCHEMA_IMAGE = "foxglove.RawImage"
SCHEMA_GROUNDTRUTH_POSE = "foxglove.PoseInFrame"
SCHEMA_EVENT = "visland.Event"
SCHEMA_OBSERVATION = "visland.Observation"
SCHEMA_GROUNDTRUTH = "visland.GroundTruth"
SCHEMA_COMMAND = "visland.Command"
SCHEMA_POLICY_ESTIMATE = "visland.PolicyEstimate"
SCHEMA_EPISODE_SCENARIO = "visland.EpisodeScenario"
SCHEMA_EPISODE_RESULT = "visland.EpisodeResult"
SCHEMA_AUTOPILOT_COMMAND = "visland.AutopilotCommand"
SCHEMA_RX_ERROR = "visland.RxError"
SCHEMA_LINK_STATS = "visland.LinkStats"
SCHEMA_COMPANION_OBSERVATION = "visland.CompanionObservation"
SCHEMA_COMPANION_COMMAND = "visland.CompanionCommand"
SCHEMA_COMPANION_SUMMARY = "visland.CompanionSummary"
SCHEMA_COMPANION_LANDING_TARGET = "visland.CompanionLandingTarget"
SCHEMA_PRECLAND = "visland.Precland"
SCHEMA_LABEL = "visland.Label"

SCHEMAS: dict[str, str] = {
    TOPIC_IMAGE: SCHEMA_IMAGE,
    TOPIC_EVENTS: SCHEMA_EVENT,
    TOPIC_OBSERVATION: SCHEMA_OBSERVATION,
    TOPIC_GROUNDTRUTH: SCHEMA_GROUNDTRUTH,
    TOPIC_GROUNDTRUTH_POSE: SCHEMA_GROUNDTRUTH_POSE,
    TOPIC_COMMAND: SCHEMA_COMMAND,
    TOPIC_POLICY_ESTIMATE: SCHEMA_POLICY_ESTIMATE,
    TOPIC_SCENARIO: SCHEMA_EPISODE_SCENARIO,
    TOPIC_RESULT: SCHEMA_EPISODE_RESULT,
    TOPIC_AUTOPILOT_COMMAND: SCHEMA_AUTOPILOT_COMMAND,
    TOPIC_RX_ERRORS: SCHEMA_RX_ERROR,
    TOPIC_LINK_STATS: SCHEMA_LINK_STATS,
    TOPIC_COMPANION_OBSERVATION: SCHEMA_COMPANION_OBSERVATION,
    TOPIC_COMPANION_COMMAND: SCHEMA_COMPANION_COMMAND,
    TOPIC_COMPANION_SUMMARY: SCHEMA_COMPANION_SUMMARY,
    TOPIC_COMPANION_LANDING_TARGET: SCHEMA_COMPANION_LANDING_TARGET,
    TOPIC_PRECLAND: SCHEMA_PRECLAND,
    TOPIC_LABEL: SCHEMA_LABEL,
}
"""Topic → schema name for every fixed topic (``/mavlink/*/<NAME>``: :func:`mavlink_schema`)."""

_ROLLOUT_TOPICS = frozenset(
    {
        TOPIC_IMAGE,
        TOPIC_OBSERVATION,
        TOPIC_GROUNDTRUTH,
        TOPIC_GROUNDTRUTH_POSE,
        TOPIC_COMMAND,
        TOPIC_POLICY_ESTIMATE,
        TOPIC_SCENARIO,
        TOPIC_RESULT,
    }
)
LOG_KIND_TOPICS: dict[str, frozenset[str]] = {
    "rollout": _ROLLOUT_TOPICS,
    "sitl": _ROLLOUT_TOPICS
    | {TOPIC_EVENTS, TOPIC_AUTOPILOT_COMMAND, TOPIC_RX_ERRORS, TOPIC_LINK_STATS, TOPIC_PRECLAND},
    "companion": frozenset(
        {
            TOPIC_IMAGE,
            TOPIC_EVENTS,
            TOPIC_COMPANION_OBSERVATION,
            TOPIC_COMPANION_COMMAND,
            TOPIC_COMPANION_SUMMARY,
            TOPIC_COMPANION_LANDING_TARGET,
        }
    ),
}
"""The fixed topics each log kind may hold (besides ``/mavlink/in|out/<NAME>``)."""


def mavlink_schema(name: str) -> str:
    """Schema name of a logged MAVLink message ``NAME`` (``mavlink.NAME``)."""
    return "mavlink." + name
