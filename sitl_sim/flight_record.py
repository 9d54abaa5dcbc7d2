"""What a simulated flight writes into its MCAP log, and how it is read back.

Shared by the in-process rollout (``training.exec.rollout``) and the MAVLink SITL so that both paths
write the same topics (DESIGN.md "Flight logs"); read back by ``expert.relabel`` and training.
Per control step (camera frame): ``/camera/image`` (foxglove.RawImage), ``/observation`` (the
non-image Observation fields), ``/groundtruth/state`` + ``/groundtruth/pose`` (privileged), and
``/command`` (what the pilot sent for that frame). Per episode: ``/episode/scenario`` first and
``/episode/result`` last.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from companion.contract import Command, GroundTruth, Observation
from companion.contract.topics import (
    SCHEMA_COMMAND,
    SCHEMA_EPISODE_RESULT,
    SCHEMA_EPISODE_SCENARIO,
    SCHEMA_GROUNDTRUTH,
    SCHEMA_OBSERVATION,
    TOPIC_COMMAND,
    TOPIC_GROUNDTRUTH,
    TOPIC_OBSERVATION,
    TOPIC_RESULT,
    TOPIC_SCENARIO,
)
from companion.flightlog import FlightLogWriter
from sitl_sim.metrics import EpisodeResult
from sitl_sim.physics.airframe import AirframeScales
from sitl_sim.scenario import InitialState

__all__ = [
    "command_msg",
    "groundtruth_from_msg",
    "groundtruth_msg",
    "observation_from_msg",
    "observation_msg",
    "write_control_step",
    "write_episode_result",
    "write_episode_start",
]


def groundtruth_msg(gt: GroundTruth, frame_id: int) -> dict[str, Any]:
    msg = {
        "frame_id": frame_id,
        "pos_ned_m": gt.pos_ned_m,
        "vel_ned_m_s": gt.vel_ned_m_s,
        "quat_wxyz": gt.quat_wxyz,
        "rate_frd_rad_s": gt.rate_frd_rad_s,
        "accel_ned_m_s2": gt.accel_ned_m_s2,
        "rotor_thrust_n": gt.rotor_thrust_n,
    }
    if gt.wind_ned_m_s is not None:  # only in a world with wind: still-air logs are unchanged
        msg["wind_ned_m_s"] = gt.wind_ned_m_s
    return msg


def groundtruth_from_msg(msg: dict[str, Any]) -> GroundTruth:
    """Rebuild a GroundTruth from its log message (KeyError/ValueError if malformed)."""

    def vec(key: str, n: int) -> np.ndarray:
        arr = np.asarray(msg[key], dtype=float)
        if arr.shape != (n,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{key}: expected {n} finite numbers, got {msg[key]!r}")
        return arr

    return GroundTruth(
        time_s=float(msg["time_s"]),
        pos_ned_m=vec("pos_ned_m", 3),
        vel_ned_m_s=vec("vel_ned_m_s", 3),
        quat_wxyz=vec("quat_wxyz", 4),
        rate_frd_rad_s=vec("rate_frd_rad_s", 3),
        accel_ned_m_s2=vec("accel_ned_m_s2", 3),
        rotor_thrust_n=vec("rotor_thrust_n", 4),
        wind_ned_m_s=vec("wind_ned_m_s", 3) if "wind_ned_m_s" in msg else None,
    )


def observation_msg(obs: Observation) -> dict[str, Any]:
    return {
        "frame_id": obs.frame_id,
        "image_time_s": obs.image_time_s,
        "attitude_rad": obs.attitude_rad,
        "rate_frd_rad_s": obs.rate_frd_rad_s,
        "attitude_time_s": obs.attitude_time_s,
        "range_m": obs.range_m,  # NaN (invalid) is written as null
        "range_time_s": obs.range_time_s,
        "accel_frd_m_s2": obs.accel_frd_m_s2,
        "imu_time_s": obs.imu_time_s,
        # not reported (NaN) is left out, as in logs written before the field existed
        **({"hover_thrust_norm": obs.hover_thrust_norm} if obs.hover_thrust_norm > 0 else {}),
    }


def observation_from_msg(msg: dict[str, Any], image: np.ndarray) -> Observation:
    rng = msg["range_m"]
    return Observation(
        image=image,
        image_time_s=float(msg["image_time_s"]),
        attitude_rad=np.asarray(msg["attitude_rad"], dtype=float),
        rate_frd_rad_s=np.asarray(msg["rate_frd_rad_s"], dtype=float),
        attitude_time_s=float(msg["attitude_time_s"]),
        range_m=math.nan if rng is None else float(rng),
        range_time_s=float(msg["range_time_s"]),
        accel_frd_m_s2=np.asarray(msg["accel_frd_m_s2"], dtype=float),
        imu_time_s=float(msg["imu_time_s"]),
        frame_id=int(msg["frame_id"]),
        hover_thrust_norm=float(msg.get("hover_thrust_norm", math.nan)),
    )


def command_msg(cmd: Command, frame_id: int, source: str) -> dict[str, Any]:
    return {
        "frame_id": frame_id,
        "thrust_norm": cmd.thrust_norm,
        "rate_frd_rad_s": cmd.rate_frd_rad_s,
        "source": source,
    }


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
    record = {
        "seed": seed,
        "episode_index": episode_index,
        "initial_state": initial.to_dict(),
        "scenario": scenario,
    }
    if airframe is not None:
        record["airframe"] = airframe.to_dict()
    log.write(TOPIC_SCENARIO, SCHEMA_EPISODE_SCENARIO, 0.0, record)


def write_control_step(
    log: FlightLogWriter,
    obs: Observation,
    gt: GroundTruth,
    command: Command | None,
    source: str,
) -> None:
    """One camera frame: image, observation, ground truth (+ pose) and the command sent."""
    t = gt.time_s
    log.write_image(obs.image_time_s, obs.image, obs.frame_id)
    log.write(TOPIC_OBSERVATION, SCHEMA_OBSERVATION, obs.image_time_s, observation_msg(obs))
    log.write(TOPIC_GROUNDTRUTH, SCHEMA_GROUNDTRUTH, t, groundtruth_msg(gt, obs.frame_id))
    log.write_pose(t, gt.pos_ned_m, gt.quat_wxyz)
    if command is not None:
        log.write(TOPIC_COMMAND, SCHEMA_COMMAND, t, command_msg(command, obs.frame_id, source))


def write_episode_result(log: FlightLogWriter, result: EpisodeResult) -> None:
    log.write(TOPIC_RESULT, SCHEMA_EPISODE_RESULT, result.time_s, result.to_dict())
