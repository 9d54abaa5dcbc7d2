"""Stage ``eval``: the Table 3 rows — expert, BC, DAgger and vision policies flown on the
evaluation seed (disjoint from training and validation) — and the inference timing, into
``metrics.json``."""

from __future__ import annotations

import json
from typing import Any

import torch

from companion.flightlog import jsonable
from training.run_folder import Run
from training.stages.records import (
    STAGES,
    BcRecord,
    DaggerRecord,
    EvalRecord,
    EvalRow,
    Metrics,
    Rows,
    StageRecords,
    VisionRecord,
)
from training.stages.selection import evaluate

__all__ = ["inference_timing", "run"]


def inference_timing(vision_checkpoint: str, steps: int = 300) -> dict[str, Any]:
    """Per-step compute of the MPC expert vs the shipped policy, same process, one thread."""
    from expert.bench import bench_mpc
    from training.bench_policy import bench_policy

    torch.set_num_threads(1)
    policy = bench_policy(vision_checkpoint, steps=steps)
    mpc = bench_mpc()
    return {"policy": policy, "mpc": mpc}


def run(r: Run) -> EvalRecord:
    p = r.profile
    vision = r.need("vision", VisionRecord).checkpoint
    policies = [
        ("expert", "expert", False),
        ("bc", r.need("bc", BcRecord).checkpoint, False),
        ("dagger", r.need("dagger", DaggerRecord).checkpoint, False),
        ("vision", vision, True),
    ]
    rows = {}
    for row, policy, camera in policies:
        report = evaluate(r, policy, p.eval_episodes, p.eval_seed, camera, r.progress)
        rows[row] = report
        r.say(
            f"eval {row}: mean error {report['landing_error_m']['mean']:.3f} m, "
            f"max {report['landing_error_m']['max']:.3f} m, success "
            f"{100 * report['success_rate']:.1f} %"
        )
    path = r.root / "metrics.json"
    metrics = Metrics(
        profile=p,
        git_commit=r.commit,
        eval_seed=p.eval_seed,
        episodes=p.eval_episodes,
        rows=Rows(**{k: EvalRow.from_dict(jsonable(v), f"eval {k}") for k, v in rows.items()}),
        timing=inference_timing(vision),
        stages=StageRecords(**{s: r.done(s) for s in STAGES if s != "eval"}),
    )
    path.write_text(json.dumps(jsonable(metrics.to_dict()), indent=2))
    return r.finish(EvalRecord(stage="eval", git_commit=r.commit, metrics=str(path)))
