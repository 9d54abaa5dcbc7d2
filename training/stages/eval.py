"""Stage ``eval``: the Table 3 rows — expert, BC, DAgger and vision policies flown on the
evaluation seed (disjoint from training and validation) — and the inference timing, into
``metrics.json``."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from training.evaluate import EvalConfig
from training.evaluate import evaluate as evaluate_policy
from training.run_folder import Run
from training.stage_records import (
    STAGES,
    BcRecord,
    DaggerRecord,
    EvalRecord,
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


def fly_suite(r: Run, policy: str, name: str, suite_file: Path | None = None) -> str:
    """A suite (``suite_file``, default the profile's) flown by ``policy`` (a checkpoint) into
    ``<run>/<name>``; a finished file of the same checkpoint bytes (sha256) and suite is kept (the
    stage resumes past it; a redone vision stage's new ``vision.pt`` is flown again)."""
    from companion.files import sha256_file
    from training.provenance import REPO
    from training.suite import format_suite_table, load_suite, run_suite

    p = r.profile
    if suite_file is None:
        assert p.eval_suite is not None
        suite_file = REPO / p.eval_suite
    path = r.root / name
    suite = load_suite(suite_file)
    sha = sha256_file(policy)
    if path.exists():
        try:
            done = json.loads(path.read_text())
            if done.get("policy_sha256") == sha and done.get("suite") == suite.path:
                return str(path)
        except ValueError:
            pass  # half-written: fly it again
    flying = EvalConfig(policy, render_camera=True, progress=r.progress, backend=r.backend)
    report = run_suite(suite, flying, seed=p.eval_seed)
    report = replace(report, policy_sha256=sha)
    format_suite_table(report, sys.stderr)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(report.to_json(indent=1))
    tmp.replace(path)
    return str(path)


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
                render_camera=camera,
                progress=r.progress,
                backend=r.backend,
            )
        )
        rows[row] = report
        s = report.summary
        r.say(
            f"eval {row}: mean error {s.landing_error_m.mean:.3f} m, "
            f"max {s.landing_error_m.max:.3f} m, success {100 * s.success_rate:.1f} %"
        )
    suite = suite_baseline = None
    if p.eval_suite is not None:
        suite = fly_suite(r, vision, "suite.json")
        if p.eval_suite_baseline is not None:
            from training.provenance import REPO

            suite_baseline = fly_suite(r, str(REPO / p.eval_suite_baseline), "suite_baseline.json")
    path = r.root / "metrics.json"
    metrics = Metrics(
        profile=p,
        git_commit=r.commit,
        eval_seed=p.eval_seed,
        episodes=p.eval_episodes,
        rows=Rows(**rows),
        timing=inference_timing(vision),
        stages=StageRecords(**{s: r.done(s) for s in STAGES if s != "eval"}),
        suite=suite,
        suite_baseline=suite_baseline,
    )
    path.write_text(metrics.to_json())
    return r.finish(EvalRecord(stage="eval", git_commit=r.commit, metrics=str(path)))
