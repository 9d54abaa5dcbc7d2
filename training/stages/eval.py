"""Stage ``eval``: the Table 3 rows — expert, BC, DAgger and vision policies flown on the
evaluation seed (disjoint from training and validation) — and the inference timing, into
``metrics.json``."""

from __future__ import annotations

import json
import sys
from typing import Any

import torch

from companion.flightlog import jsonable
from training.evaluate import EvalConfig
from training.evaluate import evaluate as evaluate_policy
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
        # the run's scenario (a worlds run: the paper's, configs/scenario.toml), never pooled
        # over training worlds: Table 3 rows compare with the paper's
        report = evaluate_policy(
            EvalConfig(
                policy=policy,
                episodes=p.eval_episodes,
                seed=p.eval_seed,
                scenario=r.scenario_path,
                workers=p.workers,
                render_camera=camera,
                progress=r.progress,
            )
        )
        rows[row] = report
        r.say(
            f"eval {row}: mean error {report['landing_error_m']['mean']:.3f} m, "
            f"max {report['landing_error_m']['max']:.3f} m, success "
            f"{100 * report['success_rate']:.1f} %"
        )
    suite = None
    if p.eval_suite is not None:
        from training.provenance import REPO
        from training.suite import format_suite_table, load_suite, run_suite

        report = run_suite(
            load_suite(REPO / p.eval_suite),
            vision,
            seed=p.eval_seed,
            workers=p.workers,
            render_camera=True,
            progress=r.progress,
        )
        format_suite_table(report, sys.stderr)
        suite_path = r.root / "suite.json"
        suite_path.write_text(json.dumps(jsonable(report), indent=1))
        suite = str(suite_path)
    path = r.root / "metrics.json"
    metrics = Metrics(
        profile=p,
        git_commit=r.commit,
        eval_seed=p.eval_seed,
        episodes=p.eval_episodes,
        rows=Rows(**{k: EvalRow.from_dict(jsonable(v), f"eval {k}") for k, v in rows.items()}),
        timing=inference_timing(vision),
        stages=StageRecords(**{s: r.done(s) for s in STAGES if s != "eval"}),
        suite=suite,
    )
    path.write_text(json.dumps(jsonable(metrics.to_dict()), indent=2))
    return r.finish(EvalRecord(stage="eval", git_commit=r.commit, metrics=str(path)))
