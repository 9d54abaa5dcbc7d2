"""Fly policies in process: one episode, many episodes in parallel workers, expert collection.

The in-process path writes the same flight-log topics as the MAVLink SITL
(``sitl_sim.flight_record``), so ``visland relabel`` and training read both alike.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, is_dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from companion.contract.record_base import RecordError
from companion.contract.records import EpisodeResultRecord
from companion.contract.topics import TOPIC_RESULT
from companion.flightlog import FlightLogError, FlightLogWriter, read_log
from companion.policy_net.guard import PadNotFound
from companion.states import FailsafeReason
from sitl_sim.config import SimConfig, VehicleConfig
from sitl_sim.env import LandingEnv
from sitl_sim.flight_record import (
    write_control_step,
    write_episode_result,
    write_episode_start,
)
from sitl_sim.metrics import EpisodeResult
from sitl_sim.scenario import Scenario
from training.provenance import git_commit
from training.reports import EpisodeRow

__all__ = [
    "EpisodeOutcome",
    "RolloutSpec",
    "VehicleModelPilot",
    "episode_pilot",
    "fly_episode",
    "fly_in_this_process",
    "log_name",
    "make_policy",
    "run_episodes",
]


Settings = tuple[tuple[str, Any], ...]
"""(key, value) pairs of :data:`companion.policy_net.ESTIMATOR_FIELDS` (hashable: a spec is a
cache key)."""


def make_policy(name: str, env: LandingEnv, settings: Settings = ()):
    """``expert`` (the MPC), ``cascade`` (the PD baseline), or a checkpoint path;
    ``settings``: estimator and guard values a checkpoint flies with instead of its own
    (``NetConfig.with_settings``)."""
    if settings and name in ("expert", "cascade"):
        raise ValueError(f"estimator settings: {name!r} has no estimator (a checkpoint has)")
    if name == "expert":
        from expert.mpc import MpcExpert

        return MpcExpert(env.vehicle, env.sim_config)
    if name == "cascade":
        from expert.cascade import CascadeLander

        return CascadeLander(env.vehicle, env.sim_config.planet)
    if not Path(name).exists():
        raise FileNotFoundError(
            f"policy {name!r}: not 'expert', 'cascade' or an existing checkpoint file"
        )
    import torch

    from companion.policy_net import load_policy

    torch.set_num_threads(1)  # one policy per worker process; workers run in parallel
    return load_policy(name).with_settings(dict(settings))


@runtime_checkable
class VehicleModelPilot(Protocol):
    """A pilot that carries a model of the vehicle it flies (the MPC expert, the cascade
    lander): ``for_vehicle(v)`` is the same pilot built for vehicle ``v``."""

    def for_vehicle(self, vehicle: VehicleConfig) -> Any: ...


def episode_pilot(policy, vehicle: VehicleConfig):
    """Who flies an episode of ``vehicle`` (the env's ``episode_vehicle``): a model-based
    privileged pilot is rebuilt for that airframe (cached by vehicle; the nominal vehicle is the
    pilot itself), as it reads the true wind; a learned policy flies whatever airframe it is in,
    as it must on hardware."""
    return policy.for_vehicle(vehicle) if isinstance(policy, VehicleModelPilot) else policy


@dataclass(frozen=True)
class RolloutSpec:
    """What a worker needs to fly episodes: picklable, so it crosses process boundaries."""

    policy: str = "expert"
    seed: int = 0
    scenario: str | Scenario | None = None
    """A scenario file, or a checked scenario (e.g. a benchmark suite's inline condition)."""
    vehicle: str | VehicleConfig | None = None
    sim: str | SimConfig | None = None
    render_camera: bool = True
    log_dir: str | None = None
    """Write one MCAP flight log per episode here (None: no logs)."""
    settings: Settings = ()
    """A checkpoint's estimator and guard values replaced, as (key, value) pairs
    (``visland eval --estimator``; ``NetConfig.with_settings``)."""


@dataclass(frozen=True)
class EpisodeOutcome:
    """How one episode went, plus the pilot's counters (e.g. MPC solve statistics)."""

    seed: int
    episode_index: int
    result: EpisodeResult
    steps: int
    log_path: str | None = None
    policy_stats: dict[str, int] = field(default_factory=dict)
    touchdown_ne_m: tuple[float, float] | None = None
    """(north, east) of the vehicle centre relative to the pad centre where
    ``result.landing_error_m`` was measured: at first ground contact, or at the timeout when
    the vehicle never landed (``result.landed`` False); its norm is the landing error."""

    def row(self) -> EpisodeRow:
        where = self.touchdown_ne_m
        return EpisodeRow(
            seed=self.seed,
            episode=self.episode_index,
            **self.result.to_dict(),
            touchdown_ne_m=None if where is None else (float(where[0]), float(where[1])),
            steps=self.steps,
            log=self.log_path,
            policy_counts=dict(self.policy_stats),
        )


def _policy_counts(policy) -> dict[str, int]:
    """A policy's integer counters (e.g. the MPC's solve statistics), if it keeps any."""
    stats = getattr(policy, "stats", None)
    if stats is None or not is_dataclass(stats):
        return {}
    return {k: int(v) for k, v in asdict(stats).items()}


def log_name(seed: int, index: int) -> str:
    return f"ep_s{seed}_{index:05d}.mcap"


def fly_episode(
    env: LandingEnv,
    policy,
    seed: int,
    index: int,
    log_path: Path | None = None,
    source: str = "policy",
    metadata: dict[str, Any] | None = None,
) -> EpisodeOutcome:
    """Fly episode ``index`` of ``seed`` with ``policy`` (``act(obs, gt, state)``; a
    :class:`VehicleModelPilot` flies as :func:`episode_pilot` of the episode's vehicle).

    With ``log_path``, the flight log is written to ``<log_path>.part`` and renamed when the
    episode has ended, so an existing ``.mcap`` is always a complete flight.
    """
    env.reset(seed=seed, options={"episode_index": index})
    sim = env.simulator
    policy = episode_pilot(policy, env.episode_vehicle)
    stats_before = _policy_counts(policy)
    log = None
    tmp = None
    if log_path is not None:
        tmp = log_path.with_suffix(".mcap.part")
        # config.vehicle is the vehicle file; the drawn factors, if any, go with the episode,
        # and so does the pad design drawn (its size: what a log's scene draws)
        drawn = {k: env.drawn[k] for k in ("airframe", "pad") if k in env.drawn}
        meta = {
            "config": {
                "vehicle": env.vehicle.to_dict(),
                "sim": env.sim_config.to_dict(),
                "scenario": env.scenario.to_dict(),
            },
            "episode": {"seed": seed, "episode_index": index, "source": source, **drawn},
            **(metadata or {}),
        }
        log = FlightLogWriter(tmp, meta, reproducible=True)
        write_episode_start(
            log, env.initial_state, env.scenario.to_dict(), seed, index, env.airframe
        )
    try:
        state = policy.initial_state()
        steps = 0
        frame = 0
        truth = sim.ground_truth()
        obs = sim.observe(frame_id=frame, truth=truth)
        max_steps = math.ceil(env.sim_config.episode_timeout_s * env.sim_config.control_rate_hz)
        result = None
        where_ne = None
        while result is None:
            try:
                command, state = policy.act(obs, truth, state)
            except PadNotFound:  # the guard gave up in the air: an abort, not a touchdown
                result = EpisodeResult.aborted_by(
                    FailsafeReason.PAD_NOT_FOUND, truth.time_s, truth.pad_relative[0]
                )
                where_ne = truth.pad_relative[0]
                break
            if log is not None:
                write_control_step(log, obs, truth, command, source, state)
            contact = sim.step(command)
            steps += 1
            truth = sim.ground_truth()
            if contact is not None:
                result = EpisodeResult.from_contact(contact)
                # relative to the pad: in its frame on a site (forward, right), else N, E
                where_ne = contact.pos_ned_m if contact.pad is None else contact.pad.pos_m
            elif steps >= max_steps:
                result = EpisodeResult.timeout(truth.time_s, *truth.pad_relative)
                where_ne = truth.pad_relative[0]
            else:
                frame += 1
                obs = sim.observe(frame_id=frame, truth=truth)
        if log is not None:
            write_episode_result(log, result)
    finally:
        if log is not None:
            log.close()
    if log_path is not None and tmp is not None:
        tmp.replace(log_path)
    delta = {k: v - stats_before.get(k, 0) for k, v in _policy_counts(policy).items()}
    return EpisodeOutcome(
        seed=seed,
        episode_index=index,
        result=result,
        steps=steps,
        log_path=str(log_path) if log_path is not None else None,
        policy_stats=delta,
        touchdown_ne_m=(float(where_ne[0]), float(where_ne[1])),
    )


# --------------------------------------------------------------------------- parallel workers

_WORKER: dict[str, Any] = {}


def _worker_init(spec: RolloutSpec, policy_file: str | None = None) -> None:
    """This process's env and policy for ``spec``; ``policy_file``: where this host keeps the
    checkpoint ``spec.policy`` names (a Ray node's copy), the name staying ``spec.policy``."""
    env = LandingEnv(
        vehicle=spec.vehicle,
        sim=spec.sim,
        scenario=spec.scenario,
        render_camera=spec.render_camera,
    )
    _WORKER["env"] = env
    _WORKER["policy"] = make_policy(policy_file or spec.policy, env, spec.settings)
    _WORKER["spec"] = spec
    _WORKER["commit"] = git_commit()


def _worker_run(index: int) -> EpisodeOutcome:
    spec: RolloutSpec = _WORKER["spec"]
    log_path = Path(spec.log_dir) / log_name(spec.seed, index) if spec.log_dir else None
    return fly_episode(
        _WORKER["env"],
        _WORKER["policy"],
        spec.seed,
        index,
        log_path,
        source=spec.policy,
        metadata={"provenance": {"git_commit": _WORKER["commit"], "policy": spec.policy}},
    )


def fly_in_this_process(spec: RolloutSpec, index: int, policy_file: str | None = None):
    """Episode ``index`` of ``spec`` in this (long-lived worker) process, keeping the env and
    policy between calls of the same spec (a Ray task's body: ``training.exec.ray_backend``)."""
    key = (spec, policy_file)
    if _WORKER.get("key") != key:
        if "env" in _WORKER:
            _WORKER["env"].close()
            _WORKER.clear()
        _worker_init(spec, policy_file)
        _WORKER["key"] = key
    return _worker_run(index)


def run_episodes(
    spec: RolloutSpec,
    indices: list[int],
    workers: int = 1,
    on_done: Callable[[EpisodeOutcome], None] | None = None,
) -> list[EpisodeOutcome]:
    """Fly the given episode indices in ``workers`` spawn processes (one: this process);
    results sorted by index. The local backend's episodes (``training.exec.backend``)."""
    outcomes: list[EpisodeOutcome] = []

    def consume(it: Iterator[EpisodeOutcome]) -> None:
        for out in it:
            outcomes.append(out)
            if on_done is not None:
                on_done(out)

    if workers <= 1 or len(indices) <= 1:
        _worker_init(spec)
        try:
            consume(_worker_run(i) for i in indices)
        finally:
            _WORKER["env"].close()
            _WORKER.clear()
    else:
        # spawn: workers never inherit a pybullet client or torch threads from the parent.
        ctx = get_context("spawn")
        with ProcessPoolExecutor(
            max_workers=workers, mp_context=ctx, initializer=_worker_init, initargs=(spec,)
        ) as pool:
            consume(pool.map(_worker_run, indices, chunksize=1))
    return sorted(outcomes, key=lambda o: o.episode_index)


def completed_episode(path: Path) -> bool:
    """True when ``path`` is a complete, readable flight log with the result of a flight that
    was not aborted (a SITL stopped mid-episode logs ``aborted``: that episode flies again)."""
    try:
        log = read_log(path, topics=[TOPIC_RESULT])
    except FlightLogError:
        return False
    results = log.topic(TOPIC_RESULT)
    if log.truncated or not results:
        return False
    try:
        return EpisodeResultRecord.from_dict(results[-1]).aborted is not True
    except (RecordError, TypeError):
        return False  # a result message that is not a result: fly the episode again
