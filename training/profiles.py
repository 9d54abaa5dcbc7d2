"""Budgets of a pipeline run: :class:`Profile`, the named :data:`PROFILES`, and the
pipeline's error type (no torch here: reports read a run's profile too)."""

from __future__ import annotations

from dataclasses import dataclass

from training.record import Record
from training.seeds import EVAL_SEED
from training.transport import Transport

__all__ = ["PROFILES", "ROLLOUT_TRANSPORTS", "PipelineError", "Profile"]

ROLLOUT_TRANSPORTS = (Transport.MAVLINK.value, Transport.INPROCESS.value)
"""The values of the profile key ``rollouts`` (:class:`training.transport.Transport`)."""


class PipelineError(ValueError):
    """A stage cannot run (missing prerequisite, unusable data); names the stage and file."""


@dataclass(frozen=True)
class Profile(Record):
    """Budgets of one pipeline run (see PROFILES)."""

    name: str
    collect_episodes: int
    bc_steps: int
    dagger_rounds: int
    dagger_rollouts: int
    dagger_steps: int
    perception_epochs: int
    perception_frame_stride: int
    perception_pose_frames: int
    """Frames rendered at sampled poses (tilted, low, pad out of view) added to the expert
    frames for CNN training (``training.perception_data``)."""
    vision_bc_steps: int
    vision_rounds: int
    vision_rollouts: int
    vision_steps: int
    eval_episodes: int
    validation_episodes: int = 20
    """Episodes (seed ``validation_seed``, disjoint from training and eval) that pick the best
    checkpoint of a stage: BC or a DAgger round, vision BC or a vision round."""
    validation_seed: int = 500
    collect_seed: int = 0
    dagger_seed: int = 100
    vision_seed: int = 200
    eval_seed: int = EVAL_SEED
    batch_segments: int = 32
    lr: float = 1e-3
    finetune_lr: float = 5e-4
    buffer_capacity: int = 400
    segment_steps: int = 25
    burn_in_steps: int = 0
    workers: int = 2
    """Parallel in-process workers, or SITL + companion pairs for ``mavlink`` rollouts."""
    rollouts: str = Transport.MAVLINK.value
    """How DAgger learner rollouts fly: ``mavlink`` (default) — the SITL and the companion as
    separate processes over UDP in lockstep, ``workers`` pairs side by side, the SITL's flight
    logs relabelled; ``inprocess`` — the gymnasium env in worker processes (faster, same
    physics). Expert collection, validation and evaluation fly in process either way."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.rollouts not in ROLLOUT_TRANSPORTS:
            raise PipelineError(
                f"profile {self.name!r}: rollouts = {self.rollouts!r}; expected one of "
                f"{', '.join(ROLLOUT_TRANSPORTS)}"
            )


PROFILES: dict[str, Profile] = {
    # A smoke run of every stage: <= 10 min on 2 cores. Its numbers are not the paper's.
    "quick": Profile(
        name="quick",
        collect_episodes=40,
        bc_steps=1500,
        dagger_rounds=1,
        dagger_rollouts=20,
        dagger_steps=800,
        perception_epochs=15,
        perception_frame_stride=2,
        perception_pose_frames=4000,
        vision_bc_steps=500,
        vision_rounds=1,
        vision_rollouts=16,
        vision_steps=500,
        eval_episodes=20,
        validation_episodes=6,
    ),
    # Paper 4.3 adapted to 2 CPU cores (<= 60 min): 200 expert flights, BC, 2 privileged DAgger
    # rounds of 60 learner rollouts, CNN on the expert frames, 1 vision DAgger round; 300
    # evaluation episodes per Table 3 row.
    "paper": Profile(
        name="paper",
        collect_episodes=200,
        bc_steps=6000,
        dagger_rounds=2,
        dagger_rollouts=60,
        dagger_steps=3000,
        perception_epochs=5,
        perception_frame_stride=2,
        perception_pose_frames=24000,
        vision_bc_steps=2000,
        vision_rounds=1,
        vision_rollouts=60,
        vision_steps=2500,
        eval_episodes=300,
        validation_episodes=12,
    ),
}
