"""Per-step inference time of the shipped policy vs a paper-style network, same process.

The paper (section 6) reports 0.0132 s per control step for its CNN+LSTM and 0.125 s for its
MPC, but gives no layer sizes. The baseline here is our reconstruction of that kind of network —
a conventional CNN (32-64-128 channels, flatten, 256-unit MLP) regressing the 2-D position, then
a 128-unit LSTM and MLP head — timed on the same machine in the same run, so the ratio is fair
even on a shared, noisy CPU. Both run one thread, batch 1, as on a companion computer.

``runtime = "onnx"`` adds the checkpoint on ONNX Runtime (the board's runtime) twice: interleaved
with the torch nets (every step right after the 2.4M-parameter paper-style net has gone through
the caches: the ratio to torch), and alone (consecutive steps, nothing else in between). Without
torch (a board with ``visland[companion]``) only the second runs, on the export beside the
checkpoint — the graphs the companion flies.
"""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.contract import GroundTruth, Observation
from companion.policy_net import PolicyCore
from companion.runtime import installed

__all__ = ["bench_policy", "paper_style_net"]


def paper_style_net():
    """CNN-MLP position regressor + LSTM-MLP controller of the paper's Fig. 2 kind (torch)."""
    import torch
    from torch import nn

    class PaperStyleNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.cnn = nn.Sequential(
                nn.Conv2d(1, 32, 5, stride=2, padding=2),
                nn.ReLU(),
                nn.Conv2d(32, 64, 3, stride=2, padding=1),
                nn.ReLU(),
                nn.Conv2d(64, 128, 3, stride=2, padding=1),
                nn.ReLU(),
                nn.Conv2d(128, 128, 3, stride=2, padding=1),
                nn.ReLU(),
                nn.Flatten(),
                nn.Linear(128 * 8 * 8, 256),
                nn.ReLU(),
                nn.Linear(256, 2),
            )
            self.lstm = nn.LSTM(2 + 9, 128, batch_first=True)
            self.head = nn.Sequential(nn.Linear(128, 128), nn.ReLU(), nn.Linear(128, 4))

        def forward(self, image, aux, state):
            pos = self.cnn(image)
            h, state = self.lstm(torch.cat([pos, aux], dim=1)[:, None], state)
            return self.head(h[:, 0]), state

    return PaperStyleNet()


def _observation(rng: np.random.Generator, frame: int) -> Observation:
    return Observation(
        image=rng.integers(0, 256, (128, 128), dtype=np.uint8),
        image_time_s=frame * 0.1,
        attitude_rad=rng.normal(0, 0.05, 3),
        rate_frd_rad_s=rng.normal(0, 0.05, 3),
        attitude_time_s=frame * 0.1,
        range_m=float(rng.uniform(5, 90)),
        range_time_s=frame * 0.1,
        accel_frd_m_s2=np.array([0.0, 0.0, -9.8]) + rng.normal(0, 0.05, 3),
        imu_time_s=frame * 0.1,
        frame_id=frame,
    )


def _stats(samples: list[float]) -> dict[str, float]:
    arr = np.array(samples) * 1e3
    return {
        "median_ms": float(np.median(arr)),
        "mean_ms": float(arr.mean()),
        "std_ms": float(statistics.pstdev(arr)),
        "p99_ms": float(np.percentile(arr, 99)),
    }


def _onnx_twin(checkpoint: str, folder: Path) -> PolicyCore:
    """``checkpoint`` exported to ONNX in ``folder`` (a copy: nothing is written beside the
    original) and loaded on ONNX Runtime, one intra-op thread."""
    from companion.onnx_export import export_onnx
    from companion.onnx_runtime import load_onnx_policy

    copy = folder / Path(checkpoint).name
    shutil.copyfile(checkpoint, copy)
    export_onnx(copy)
    return load_onnx_policy(copy, threads=1)


def bench_policy(
    checkpoint: str | None = None, steps: int = 300, seed: int = 0, runtime: str = "torch"
) -> dict[str, Any]:
    """Time ``act()`` of the policy (shipped size if no checkpoint) and the paper-style net;
    with ``runtime = "onnx"`` the same checkpoint on ONNX Runtime too (exported to a temporary
    copy), interleaved in one run (``onnx``, ``onnx_vs_torch``) and alone (``onnx_alone``).
    Without torch, ``runtime = "onnx"`` times the export beside the checkpoint alone (the
    other keys are absent)."""
    if runtime not in ("torch", "onnx"):
        raise ValueError(f"runtime must be 'torch' or 'onnx', got {runtime!r}")
    if runtime == "onnx" and checkpoint is None:
        raise ValueError("bench policy --runtime onnx needs a checkpoint (an exported network)")
    if runtime == "onnx" and not installed("torch"):
        from companion.onnx_runtime import load_onnx_policy

        res = _bench_alone(load_onnx_policy(checkpoint, threads=1), steps, seed)
        return {"checkpoint": checkpoint, "steps": steps, "threads": 1, "onnx_alone": res}
    with tempfile.TemporaryDirectory(prefix="visland_bench_onnx_") as tmp:
        onnx = _onnx_twin(checkpoint, Path(tmp)) if runtime == "onnx" else None
        res = _bench(checkpoint, steps, seed, onnx)
        if onnx is not None:
            res["onnx_alone"] = _bench_alone(onnx, steps, seed)
        return res


def _observations_for(policy: PolicyCore, steps: int, seed: int):
    """``steps`` random observations, and the ground truth a privileged policy needs."""
    rng = np.random.default_rng(seed)
    obs = [_observation(rng, i) for i in range(steps)]
    gt = None
    if policy.privileged:
        gt = GroundTruth(0.0, np.array([1.0, -1.0, -50.0]), np.zeros(3), np.eye(4)[0], np.zeros(3))
    return obs, gt


def _bench_alone(policy: PolicyCore, steps: int, seed: int) -> dict[str, Any]:
    """``act()`` over consecutive steps with nothing else in between (after 20 warm-up steps)."""
    obs, gt = _observations_for(policy, steps, seed)
    state = policy.initial_state()
    for _ in range(20):
        _, state = policy.act(obs[0], gt, state)
    state, times = policy.initial_state(), []
    for o in obs:
        t = time.perf_counter()
        _, state = policy.act(o, gt, state)
        times.append(time.perf_counter() - t)
    return {**_stats(times), "kind": policy.config.kind}


def _bench(
    checkpoint: str | None, steps: int, seed: int, onnx: PolicyCore | None
) -> dict[str, Any]:
    import torch

    from companion.policy_net import load_policy, untrained_policy

    torch.set_num_threads(1)
    policy = load_policy(checkpoint) if checkpoint else untrained_policy(seed)
    obs, gt = _observations_for(policy, steps, seed)
    torch.manual_seed(seed)
    paper = paper_style_net().eval()
    ours, theirs, on_onnx = [], [], []
    state = policy.initial_state()
    ostate = onnx.initial_state() if onnx is not None else None
    pstate = None
    for _ in range(20):  # warm-up (allocator, oneDNN kernels)
        _, state = policy.act(obs[0], gt, state)
        if onnx is not None:
            _, ostate = onnx.act(obs[0], gt, ostate)
        with torch.inference_mode():
            _, pstate = paper(torch.zeros(1, 1, 128, 128), torch.zeros(1, 9), pstate)
    state, pstate = policy.initial_state(), None
    ostate = onnx.initial_state() if onnx is not None else None
    for o in obs:  # interleaved, so load changes hit all alike
        if onnx is not None:
            t = time.perf_counter()
            _, ostate = onnx.act(o, gt, ostate)
            on_onnx.append(time.perf_counter() - t)
        t0 = time.perf_counter()
        _, state = policy.act(o, gt, state)
        t1 = time.perf_counter()
        with torch.inference_mode():
            img = torch.from_numpy(o.image).float().div(255.0)[None, None]
            aux = torch.from_numpy(
                np.concatenate([o.attitude_rad, o.rate_frd_rad_s, o.accel_frd_m_s2]).astype(
                    np.float32
                )
            )[None]
            _, pstate = paper(img, aux, pstate)
        t2 = time.perf_counter()
        ours.append(t1 - t0)
        theirs.append(t2 - t1)
    n_ours = sum(p.numel() for p in policy.control.parameters()) + (
        sum(p.numel() for p in policy.perception.parameters()) if policy.perception else 0
    )
    res = {
        "checkpoint": checkpoint or "untrained (shipped size)",
        "kind": policy.config.kind,
        "steps": steps,
        "threads": 1,
        "shipped": {**_stats(ours), "parameters": int(n_ours)},
        "paper_style": {
            **_stats(theirs),
            "parameters": int(sum(p.numel() for p in paper.parameters())),
        },
        "paper_reported_ms": 13.2,
    }
    res["speedup_vs_paper_style"] = res["paper_style"]["median_ms"] / res["shipped"]["median_ms"]
    if onnx is not None:
        res["onnx"] = _stats(on_onnx)
        res["onnx_vs_torch"] = res["shipped"]["median_ms"] / res["onnx"]["median_ms"]
    return res
