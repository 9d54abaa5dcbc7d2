"""The one policy interface shared by the MPC expert and every learned policy.

A policy maps what it may see to a :class:`~companion.contract.Command`, with its recurrent state
passed in and returned explicitly (as SB3's ``PolicyPredictor`` and cleanrl's LSTM agents do), so
the rollout loop, the relabeller and the evaluator never ask which policy they hold::

    state = policy.initial_state()
    for each control step:
        command, state = policy.act(observation, groundtruth, state)

``groundtruth`` is the privileged channel (:class:`~companion.contract.GroundTruth`): the
simulator passes its true state, the companion on a SITL link passes ODOMETRY read as a
GroundTruth, hardware passes ``None``. A *privileged* policy (the MPC expert, the LSTM-only policies
of the paper's Table 3) needs it and raises :class:`MissingGroundTruthError` without it; a
deployable policy must accept ``None`` and never read it.
"""

from __future__ import annotations

from typing import Any, Protocol, TypeAlias, runtime_checkable

from companion.contract.messages import Command, GroundTruth, Observation

__all__ = ["MissingGroundTruthError", "Policy", "PolicyError", "PolicyState"]

PolicyState: TypeAlias = Any
"""A policy's recurrent state, opaque to the caller (``None``, a frozen dataclass, LSTM ``(h, c)``
tensors...). Only the policy that made it may read it; it is never mutated in place."""


class PolicyError(Exception):
    """Root of the errors a policy raises while acting."""


class MissingGroundTruthError(PolicyError, ValueError):
    """A privileged policy was asked to act without ground truth (e.g. on hardware)."""


@runtime_checkable
class Policy(Protocol):
    """Observation (+ ground truth when privileged) and state in, Command and next state out."""

    privileged: bool
    """True when :meth:`act` needs ``groundtruth`` (such a policy can never fly on hardware)."""

    def initial_state(self) -> PolicyState:
        """The state to pass to the first :meth:`act` of an episode."""
        ...

    def act(
        self,
        observation: Observation,
        groundtruth: GroundTruth | None,
        state: PolicyState,
    ) -> tuple[Command, PolicyState]:
        """One control step: the command to send now and the state for the next step.

        Args:
            observation: what the vehicle's sensors report at this control step.
            groundtruth: the simulator's privileged state at the same instant, or ``None`` on
                hardware. Deployable policies must not read it.
            state: the state returned by the previous call (or :meth:`initial_state`).

        Raises:
            MissingGroundTruthError: a privileged policy got ``groundtruth=None``.
        """
        ...
