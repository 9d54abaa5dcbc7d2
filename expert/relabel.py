"""Offline relabelling: the MPC expert's command for every control step of recorded flights.

DAgger's labels come from here (paper 3.4, eq. 2): a flight flown by anyone — the expert, a
learner, the SITL through the companion — is read back from its MCAP log and, for each camera
frame, the expert computes what it would have commanded from that frame's ground truth. Labels go
to a sibling file ``<log stem>.labels.mcap`` in ``out_dir``; the log itself is never modified.

Each step is labelled from that step alone (DAgger's expert must be a function of the learner's
state): the MPC holds the heading it finds, not the one the flight started with.

The expert is privileged: it reads the ground truth of each step and not the image, so frames are
not decoded (that keeps relabelling far above 500 steps/s per core). It labels with the vehicle
the log flew: the log's vehicle file (which must be ours) scaled by the episode's airframe factors
when the scenario had a ``[vehicle]`` section (the ``airframe`` of ``/episode/scenario``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from companion.contract import IMAGE_SIZE_PX, ContractError
from companion.contract.records import (
    TIME_S,
    CommandRecord,
    GroundTruthRecord,
    LabelRecord,
    ObservationRecord,
)
from companion.contract.topics import (
    TOPIC_COMMAND,
    TOPIC_GROUNDTRUTH,
    TOPIC_LABEL,
    TOPIC_OBSERVATION,
    TOPIC_SCENARIO,
)
from companion.files import sha256_file
from companion.flightlog import FlightLogError, FlightLogWriter, read_log
from expert.mpc import MpcExpert, MpcSolveError
from sitl_sim.config import Planet, VehicleConfig, load_sim, load_vehicle, planet
from sitl_sim.physics.airframe import AirframeScales

__all__ = ["RelabelError", "RelabelReport", "label_path", "relabel", "relabel_log"]

_BLANK = np.zeros((IMAGE_SIZE_PX, IMAGE_SIZE_PX), dtype=np.uint8)
_BLANK.setflags(write=False)


class RelabelError(Exception):
    """A log cannot be relabelled (names the file and the reason)."""


@dataclass(frozen=True)
class RelabelReport:
    """The outcome for one log.

    Attributes:
        log: the input flight log.
        labels: the label file written (None when the log failed).
        steps: control steps labelled.
        truncated: the log was cut short (crash); ``steps`` covers its readable prefix.
        error: why the log failed (None when it did not).
    """

    log: str
    labels: str | None
    steps: int
    truncated: bool
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def label_path(log: Path, out_dir: Path) -> Path:
    return out_dir / f"{log.stem}.labels.mcap"


_EXPERTS: dict[str, MpcExpert] = {}


def _expert_for(
    log_path: Path, meta: dict[str, Any], scenario_records: list[dict[str, Any]]
) -> MpcExpert:
    """The expert for the log's planet and episode vehicle, after checking the log flew our
    vehicle file."""
    config = meta.get("config")
    if not isinstance(config, dict) or "vehicle" not in config or "sim" not in config:
        raise RelabelError(f"{log_path}: no 'config' metadata with vehicle and sim")
    try:
        world = planet(config["sim"]["planet"]["name"])
    except (KeyError, TypeError) as exc:
        raise RelabelError(f"{log_path}: metadata config.sim.planet missing: {exc}") from None
    vehicle = load_vehicle()
    logged = config["vehicle"]
    ours = vehicle.to_dict()
    diff = sorted(k for k in ours if not _same_vehicle_field(k, ours, logged, vehicle, world))
    if diff:
        raise RelabelError(
            f"{log_path}: flown with another vehicle config (differs in {diff}); the expert "
            "would label it with the wrong physics"
        )
    key = world.name
    if key not in _EXPERTS:
        _EXPERTS[key] = MpcExpert(vehicle, load_sim().with_planet(world))
    return _EXPERTS[key].for_vehicle(_episode_vehicle(log_path, vehicle, scenario_records))


def _same_vehicle_field(
    key: str, ours: dict[str, Any], logged: dict[str, Any], vehicle: VehicleConfig, world: Planet
) -> bool:
    if key == "max_total_thrust_n_by_planet" and key not in logged:
        # A log from before T_max was stated per planet holds one figure, the one it flew.
        old = logged.get("max_total_thrust_n")
        return isinstance(old, int | float) and old == vehicle.max_total_thrust_n(world)
    return _jsonish(ours[key]) == logged.get(key)


def _episode_vehicle(
    log_path: Path, vehicle: VehicleConfig, scenario_records: list[dict[str, Any]]
) -> VehicleConfig:
    """The vehicle file scaled by the episode's airframe factors, if the log has any."""
    if not scenario_records or "airframe" not in scenario_records[0]:
        return vehicle
    try:
        scales = AirframeScales.from_dict(scenario_records[0]["airframe"], "airframe")
    except ValueError as exc:
        raise RelabelError(f"{log_path}: /episode/scenario: {exc}") from None
    return scales.apply(vehicle)


def _jsonish(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_jsonish(v) for v in value]
    if isinstance(value, dict):
        return {k: _jsonish(v) for k, v in value.items()}
    return value


def relabel_log(log_path: str | Path, out_dir: str | Path) -> RelabelReport:
    """Label every control step of one flight log. Raises RelabelError / FlightLogError."""
    log_path, out_dir = Path(log_path), Path(out_dir)
    log = read_log(
        log_path, topics=[TOPIC_GROUNDTRUTH, TOPIC_OBSERVATION, TOPIC_COMMAND, TOPIC_SCENARIO]
    )
    expert = _expert_for(log_path, log.metadata, log.topic(TOPIC_SCENARIO))
    truths = {m["frame_id"]: m for m in log.topic(TOPIC_GROUNDTRUTH)}
    observations = {m["frame_id"]: m for m in log.topic(TOPIC_OBSERVATION)}
    recorded = {m["frame_id"]: m for m in log.topic(TOPIC_COMMAND)}
    frames = sorted(set(truths) & set(observations))
    if not frames:
        raise RelabelError(f"{log_path}: no control steps (no ground truth + observation pairs)")
    # A step with an observation but no ground truth can only be the cut of a truncated log.
    missing = sorted(set(observations) - set(truths))
    if missing and not log.truncated:
        raise RelabelError(f"{log_path}: frames {missing[:5]} have no ground truth")
    out_dir.mkdir(parents=True, exist_ok=True)
    out = label_path(log_path, out_dir)
    tmp = out.with_suffix(".mcap.part")
    meta = {
        "labels": {
            "source_log": log_path.name,
            "source_sha256": sha256_file(log_path),
            "expert": "mpc",
            "expert_config": expert.config.to_dict(),
            "truncated_source": log.truncated,
        }
    }
    steps = 0
    with FlightLogWriter(tmp, meta, reproducible=True) as writer:
        for fid in frames:
            try:
                truth = truths[fid]
                gt = GroundTruthRecord.from_dict(truth).groundtruth(truth[TIME_S])
                obs = ObservationRecord.from_dict(observations[fid]).observation(_BLANK)
            except (KeyError, ValueError, TypeError, ContractError) as exc:
                raise RelabelError(f"{log_path}: frame {fid}: bad record: {exc}") from None
            try:
                # A fresh state every step: the MPC's only state is the heading it holds, the
                # one it found on its first step. A learner that turned would be labelled back
                # to a heading its inputs do not hold (they are heading-free), so the label
                # would not be a function of what it sees; the heading found now is.
                command, _ = expert.act(obs, gt, expert.initial_state())
            except MpcSolveError as exc:
                raise RelabelError(f"{log_path}: frame {fid}: expert failed: {exc}") from None
            rec = CommandRecord.from_dict(recorded[fid]) if fid in recorded else None
            label = LabelRecord(
                frame_id=fid,
                thrust_norm=command.thrust_norm,
                rate_frd_rad_s=command.rate_frd_rad_s,
                recorded_thrust_norm=rec.thrust_norm if rec else math.nan,
                recorded_rate_frd_rad_s=rec.rate_frd_rad_s if rec else [math.nan] * 3,
            )
            writer.write_record(TOPIC_LABEL, gt.time_s, label)
            steps += 1
    tmp.replace(out)
    return RelabelReport(str(log_path), str(out), steps, log.truncated, None)


def _safe_relabel(args: tuple[str, str]) -> RelabelReport:
    log_path, out_dir = args
    try:
        return relabel_log(log_path, out_dir)
    except (RelabelError, FlightLogError) as exc:
        return RelabelReport(log_path, None, 0, False, str(exc))


def relabel(
    logs: list[str | Path],
    out_dir: str | Path,
    workers: int = 1,
    on_done: Callable[[RelabelReport], None] | None = None,
) -> list[RelabelReport]:
    """Relabel many logs in ``workers`` processes (the local backend; ``training.exec.backend``
    has the Ray one); a failed one is reported (``error``) and the rest continue. Reports in
    the order of ``logs``."""
    jobs = [(str(p), str(out_dir)) for p in logs]
    reports = []
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            reports.append(_safe_relabel(job))
            if on_done is not None:
                on_done(reports[-1])
        return reports
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        for report in pool.map(_safe_relabel, jobs, chunksize=4):
            reports.append(report)
            if on_done is not None:
                on_done(report)
    return reports
