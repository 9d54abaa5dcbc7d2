"""What a simulated flight writes into its MCAP log, and how it is read back.

Shared by the in-process rollout (``training.exec.rollout``) and the MAVLink SITL so that both paths
write the same topics (DESIGN.md "Flight logs"); read back by ``expert.relabel`` and training.
Per control step (camera frame): ``/camera/image`` (foxglove.RawImage), ``/observation`` (the
non-image Observation fields), ``/groundtruth/state`` + ``/groundtruth/pose`` (privileged), and
``/command`` (what the pilot sent for that frame). Per episode: ``/episode/scenario`` first and
``/episode/result`` last. The records are the contract's (:mod:`companion.contract.records`):
read them back with their ``from_dict`` (``GroundTruthRecord.from_dict(m).groundtruth(m[TIME_S])``,
``ObservationRecord.from_dict(m).observation(image)``).
"""

from __future__ import annotations

from typing import Any

from companion.contract import Command, GroundTruth, Observation
from companion.contract.records import (
    TIME_S,
    CommandRecord,
    EpisodeResultRecord,
    EpisodeScenarioRecord,
    GroundTruthRecord,
    ObservationRecord,
    PolicyEstimateRecord,
    RecordError,
)
from companion.contract.topics import (
    TOPIC_COMMAND,
    TOPIC_GROUNDTRUTH,
    TOPIC_OBSERVATION,
    TOPIC_POLICY_ESTIMATE,
    TOPIC_RESULT,
    TOPIC_SCENARIO,
)
from companion.flightlog import FlightLogWriter
from sitl_sim.metrics import EpisodeResult
from sitl_sim.physics.airframe import AirframeScales
from sitl_sim.scenario import InitialState

__all__ = [
    "groundtruth_from_msg",
    "groundtruth_msg",
    "write_control_step",
    "write_episode_result",
    "write_episode_start",
]


def groundtruth_msg(gt: GroundTruth, frame_id: int) -> dict[str, Any]:
    """``gt``'s ``/groundtruth/state`` message body (``wind_ned_m_s`` only in wind)."""
    return GroundTruthRecord.from_groundtruth(gt, frame_id).to_dict()


def groundtruth_from_msg(msg: dict[str, Any]) -> GroundTruth:
    """The GroundTruth of a logged ``/groundtruth/state`` message (RecordError, a ValueError,
    if a key is missing or a vector malformed)."""
    if TIME_S not in msg:
        raise RecordError(f"{GroundTruthRecord.SCHEMA}: message has no {TIME_S!r}")
    return GroundTruthRecord.from_dict(msg).groundtruth(msg[TIME_S])


def write_episode_start(
    log: FlightLogWriter,
    initial: InitialState,
    scenario: dict[str, Any],
    seed: int,
    episode_index: int,
    airframe: AirframeScales | None = None,
) -> None:
    """``/episode/scenario``: the episode's seed, index, initial state, scenario and, with a
    ``[vehicle]`` section, its drawn airframe factors (``airframe``; left out otherwise, so a
    nominal record is unchanged; the SITL's record carries the same ``airframe``)."""
    record = EpisodeScenarioRecord(
        seed=seed,
        episode_index=episode_index,
        initial_state=initial.to_dict(),
        scenario=scenario,
        **({"airframe": airframe.to_dict()} if airframe is not None else {}),
    )
    log.write_record(TOPIC_SCENARIO, 0.0, record)


def write_control_step(
    log: FlightLogWriter,
    obs: Observation,
    gt: GroundTruth,
    command: Command | None,
    source: str,
    policy_state: Any = None,
) -> None:
    """One camera frame: image, observation, ground truth (+ pose), the command sent and, for
    a learned policy (``policy_state`` with perception or an estimator), its estimate."""
    t = gt.time_s
    log.write_image(obs.image_time_s, obs.image, obs.frame_id)
    log.write_record(TOPIC_OBSERVATION, obs.image_time_s, ObservationRecord.from_observation(obs))
    log.write_record(TOPIC_GROUNDTRUTH, t, GroundTruthRecord.from_groundtruth(gt, obs.frame_id))
    log.write_pose(t, gt.pos_ned_m, gt.quat_wxyz)
    if command is not None:
        log.write_record(
            TOPIC_COMMAND, t, CommandRecord.from_command(command, obs.frame_id, source)
        )
    estimate = PolicyEstimateRecord.from_state(policy_state, obs.frame_id)
    if estimate is not None:
        log.write_record(TOPIC_POLICY_ESTIMATE, t, estimate)


def write_episode_result(log: FlightLogWriter, result: EpisodeResult) -> None:
    log.write_record(TOPIC_RESULT, result.time_s, EpisodeResultRecord(**result.to_dict()))
