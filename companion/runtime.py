"""The policy runtime: one policy, its recurrent state held explicitly, one command per frame.

Any :class:`companion.contract.Policy` flies: the learned CNN+LSTM
(:func:`load_policy_file`: torch on the CPU, or its networks in ONNX Runtime — ``runtime =
"onnx"``, :mod:`companion.onnx_runtime`), or — wired in by ``tools/`` — the
MPC expert and the cascade lander for SITL runs. ``reset()`` starts a flight afresh
(``initial_state()``); ``step()`` never raises: a policy exception or a non-finite command comes
back as ``StepResult.error``, which the safety monitor turns into a failsafe.
"""

from __future__ import annotations

import importlib.util
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.contract import Command, GroundTruth, Observation, Policy, PolicyState
from companion.policy_net.guard import PadNotFound

_log = logging.getLogger("companion.runtime")

__all__ = [
    "RUNTIMES",
    "PolicyRuntime",
    "StepResult",
    "installed",
    "level_observation",
    "load_policy_file",
    "resolve_runtime",
]

RUNTIMES = ("auto", "torch", "onnx")
"""Backends of a learned checkpoint: ``torch`` (the checkpoint itself), ``onnx`` (its
``visland export-onnx`` graphs in ONNX Runtime; same geometry/estimator code in Python, no
torch), or ``auto`` (:func:`resolve_runtime`)."""


@dataclass(frozen=True)
class StepResult:
    """One policy step: the command (None on error), the error text, compute time (s)."""

    command: Command | None
    error: str | None
    compute_s: float
    pad_not_found: bool = False
    """The error is the landing guard's :class:`~companion.policy_net.guard.PadNotFound`: the
    flight must end without landing (not a policy fault)."""


class PolicyRuntime:
    """Holds a policy and its state for one flight at a time.

    Args:
        policy: the policy.
        name: what to call it in logs (a path, ``expert``...).
    """

    def __init__(self, policy: Policy, name: str) -> None:
        for attr in ("initial_state", "act"):
            if not callable(getattr(policy, attr, None)):
                raise TypeError(
                    f"policy {name!r}: has no {attr}() (not a companion.contract.Policy)"
                )
        self.policy = policy
        self.name = name
        self.privileged = bool(getattr(policy, "privileged", False))
        self.steps = 0
        self._state: PolicyState = None
        self._ready = False

    def warm_up(self, steps: int = 5) -> str | None:
        """Run the policy a few times on a synthetic level hover at 20 m (torch allocates and
        picks its kernels on the first calls: 5-10x slower), then forget it. Returns the error
        a policy that cannot even do that raises (None when fine)."""
        import numpy as np

        obs = level_observation()
        gt = GroundTruth(
            time_s=0.0,
            pos_ned_m=np.array([0.0, 0.0, -20.0]),
            vel_ned_m_s=np.zeros(3),
            quat_wxyz=np.array([1.0, 0.0, 0.0, 0.0]),
            rate_frd_rad_s=np.zeros(3),
        )
        self.reset()
        error = None
        for _ in range(steps):
            result = self.step(obs, gt if self.privileged else None)
            error = error or result.error
        self._ready = False
        return error

    def reset(self) -> None:
        """A new flight: the policy's initial state (LSTM zeros, MPC warm start cleared)."""
        self._state = self.policy.initial_state()
        self.steps = 0
        self._ready = True

    def next_state(self) -> PolicyState:
        """The state the next :meth:`step` starts from (a flight not started yet: its initial
        state); a region-of-interest camera cuts the next frame with its window."""
        if not self._ready:
            self.reset()
        return self._state

    def step(self, observation: Observation, groundtruth: GroundTruth | None) -> StepResult:
        if not self._ready:
            self.reset()
        t0 = time.perf_counter()
        try:
            command, state = self.policy.act(observation, groundtruth, self._state)
            if not isinstance(command, Command):
                raise TypeError(f"act() returned {type(command).__name__}, not a Command")
        except PadNotFound as exc:  # the guard gave up: a failsafe of its own
            return StepResult(None, str(exc), time.perf_counter() - t0, pad_not_found=True)
        except Exception as exc:  # any policy failure becomes a named failsafe, never a crash
            return StepResult(None, f"{type(exc).__name__}: {exc}", time.perf_counter() - t0)
        self._state = state
        self.steps += 1
        return StepResult(command, None, time.perf_counter() - t0)


def level_observation(
    range_m: float = 20.0, time_s: float = 0.0, grey: int = 96, **fields: Any
) -> Observation:
    """What a level vehicle at rest ``range_m`` above flat ground sees: a uniform ``grey``
    128x128 image, no attitude and no rates, the IMU's 1 g up (FRD z = -9.81 m/s²), every
    input stamped ``time_s``. ``fields`` replace any field (``hover_thrust_norm``,
    ``frame_id``...). The warm-up's input, and the tests' stand-in observation."""
    import numpy as np

    values: dict[str, Any] = dict(
        image=np.full((128, 128), grey, dtype=np.uint8),
        image_time_s=time_s,
        attitude_rad=np.zeros(3),
        rate_frd_rad_s=np.zeros(3),
        attitude_time_s=time_s,
        range_m=range_m,
        range_time_s=time_s,
        accel_frd_m_s2=np.array([0.0, 0.0, -9.81]),
        imu_time_s=time_s,
    )
    return Observation(**{**values, **fields})


def resolve_runtime(path: str | Path, runtime: str = "auto") -> str:
    """The backend ``runtime`` names for checkpoint ``path``: ``auto`` is ``onnx`` when
    onnxruntime is installed and the export is beside the checkpoint (what a board has), else
    ``torch``. Raises ValueError for an unknown runtime."""
    if runtime not in RUNTIMES:
        raise ValueError(f"runtime = {runtime!r}; expected one of {RUNTIMES}")
    if runtime != "auto":
        return runtime
    from companion.onnx_runtime import onnx_paths

    if onnx_paths(path)[1].is_file() and installed("onnxruntime"):
        return "onnx"
    return "torch"


def installed(module: str) -> bool:
    """Whether ``module`` can be imported here (found, and not blocked in sys.modules)."""
    try:
        return importlib.util.find_spec(module) is not None
    except ValueError:  # in sys.modules as None: its import is blocked
        return False


def load_policy_file(path: str | Path, torch_threads: int = 1, runtime: str = "auto") -> Policy:
    """A learned-policy checkpoint for the CPU (explicit LSTM state).

    ``runtime``: ``torch`` runs the checkpoint's networks in torch; ``onnx`` runs its
    ``visland export-onnx`` graphs (beside the checkpoint, checked to be exported from it) in
    ONNX Runtime, with no torch installed (the ``companion`` extra); ``auto`` (default) picks
    ``onnx`` when onnxruntime is installed and the export is there, else ``torch``.
    ``torch_threads`` limits the intra-op threads of either: on a small board one thread gives
    the steadiest latency and leaves a core to the link and the camera.

    Raises:
        companion.policy_net.CheckpointError: not a readable checkpoint (names the file).
        companion.onnx_runtime.OnnxModelError: runtime onnx: onnxruntime missing, or an ONNX
            file missing, corrupt or stale (names the file and the fix).
        ValueError: an unknown ``runtime``, or torch needed and not installed (names the
            extra to install).
    """
    chosen = resolve_runtime(path, runtime)
    _log.info("policy %s: runtime %s%s", path, chosen, " (auto)" if runtime == "auto" else "")
    if chosen == "onnx":
        from companion.onnx_runtime import load_onnx_policy

        return load_onnx_policy(path, threads=max(1, torch_threads))
    try:
        import torch
    except ImportError:
        raise ValueError(
            f"{path}: runtime torch needs torch, which is not installed: pip install "
            "'visland[torch]', or fly the ONNX export (visland export-onnx, then --runtime onnx)"
        ) from None
    if torch_threads > 0:
        torch.set_num_threads(torch_threads)
    from companion.policy_net import load_policy

    return load_policy(path)
