"""``visland bench rollouts``: episodes per minute on the local backend and on Ray, in the same
run, and what the measured costs project for a whole training profile on a cluster.

The workload is what the pipeline's rollouts fly: the expert with the camera rendered and its
flight logs written (``collect``), then the shipped vision policy the same way (DAgger and
evaluation rollouts), then the relabelling of those logs. Each is flown on the local backend
(``workers`` processes) and on Ray (``--ray``; default a local instance with as many CPUs) over
the same episodes; the Ray figure is the overhead of tasks, object transfer of the logs and
driver-side placement, as a ratio of the local rate. Starting the Ray instance is timed apart.

The projection (:func:`project_profile`) counts a profile's episodes by kind, prices them with
the CPU-seconds per episode measured here, adds the serial training time recorded in a run
folder (its stages' fit seconds), and divides the parallel part over ``nodes`` x ``cpus``, a
stage's episodes going in waves of one episode per CPU.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from training.exec.backend import Backend, LocalBackend
from training.exec.rollout import RolloutSpec
from training.profiles import Profile
from training.provenance import SHIPPED_MODEL

__all__ = ["RolloutBenchConfig", "bench_rollouts", "format_rollout_bench", "project_profile"]


@dataclass(frozen=True)
class RolloutBenchConfig:
    episodes: int = 12
    """Episodes of each kind (expert, vision policy) per backend."""
    workers: int = 0
    """Local processes (0: the CPU count)."""
    ray: str = "local"
    """Ray address (``local``: an instance started here with ``workers`` CPUs)."""
    policy: str = str(SHIPPED_MODEL)
    seed: int = 900
    run: str | None = "runs/robust"
    """A run folder whose recorded training seconds make the projection's serial part."""
    profile: str = "robust"
    nodes: tuple[int, ...] = (1, 8, 64)


def _time_kinds(backend: Backend, cfg: RolloutBenchConfig, root: Path) -> dict[str, Any]:
    """Seconds for each kind of work on ``backend`` (logs into ``root``)."""
    out: dict[str, Any] = {}
    indices = list(range(cfg.episodes))
    logs: list[Path] = []
    # two seeds: the logs (and their labels) of the two kinds never share a name
    for seed, kind, policy in (
        (cfg.seed, "expert", "expert"),
        (cfg.seed + 1, "vision", cfg.policy),
    ):
        spec = RolloutSpec(policy=policy, seed=seed, render_camera=True, log_dir=str(root / kind))
        t0 = time.perf_counter()
        outcomes = backend.episodes(spec, indices)
        out[kind] = {
            "episodes": len(outcomes),
            "seconds": time.perf_counter() - t0,
            "sim_steps": sum(o.steps for o in outcomes),
        }
        logs += [Path(o.log_path) for o in outcomes]
    t0 = time.perf_counter()
    reports = backend.relabel(logs, root / "labels")
    out["relabel"] = {
        "logs": len(reports),
        "failed": sum(1 for r in reports if r.error),
        "seconds": time.perf_counter() - t0,
    }
    return out


def bench_rollouts(cfg: RolloutBenchConfig) -> dict[str, Any]:
    """Local vs Ray over the same work, in one run; plus the projection of ``cfg.profile``."""
    from training.exec.ray_backend import RayBackend
    from training.provenance import REPO

    workers = cfg.workers or os.cpu_count() or 1
    root = Path(tempfile.mkdtemp(prefix="visland_bench_rollouts_"))
    try:
        local = _time_kinds(LocalBackend(workers), cfg, root / "local")
        t0 = time.perf_counter()
        num_cpus = workers if cfg.ray == "local" else None
        with RayBackend(cfg.ray, num_cpus=num_cpus, say=lambda _m: None) as backend:
            start_s = time.perf_counter() - t0
            ray = _time_kinds(backend, cfg, root / "ray")
            ray_cpus = backend.cpus
            retried = list(backend.retried)
        same = all(
            (root / "ray" / kind / p.name).read_bytes() == p.read_bytes()
            for kind in ("expert", "vision")
            for p in sorted((root / "local" / kind).glob("*.mcap"))
        )
    finally:
        shutil.rmtree(root, ignore_errors=True)

    def rate(kind: str, side: dict[str, Any]) -> float:
        return 60.0 * side[kind]["episodes"] / side[kind]["seconds"]

    rows = {}
    for kind in ("expert", "vision"):
        rows[kind] = {
            "local_episodes_per_min": rate(kind, local),
            "ray_episodes_per_min": rate(kind, ray),
            "ray_overhead": 1.0 - rate(kind, ray) / rate(kind, local),
            "cpu_s_per_episode": local[kind]["seconds"] * workers / local[kind]["episodes"],
        }
    rows["relabel"] = {
        "local_logs_per_min": 60.0 * local["relabel"]["logs"] / local["relabel"]["seconds"],
        "ray_logs_per_min": 60.0 * ray["relabel"]["logs"] / ray["relabel"]["seconds"],
        "ray_overhead": 1.0 - local["relabel"]["seconds"] / ray["relabel"]["seconds"],
        "cpu_s_per_log": local["relabel"]["seconds"] * workers / local["relabel"]["logs"],
    }
    total_local = sum(local[k]["seconds"] for k in ("expert", "vision", "relabel"))
    total_ray = sum(ray[k]["seconds"] for k in ("expert", "vision", "relabel"))
    result: dict[str, Any] = {
        "episodes_per_kind": cfg.episodes,
        "workers": workers,
        "ray": cfg.ray,
        "ray_cpus": ray_cpus,
        "ray_start_s": start_s,
        "retried": retried,
        "logs_identical": same,
        "kinds": rows,
        "local_s": total_local,
        "ray_s": total_ray,
        "ray_overhead": 1.0 - total_local / total_ray,
    }
    if cfg.profile:
        from training.profiles import PROFILES

        run = REPO / cfg.run if cfg.run and not Path(cfg.run).is_absolute() else cfg.run
        result["projection"] = project_profile(
            PROFILES[cfg.profile],
            cpu_s_expert=rows["expert"]["cpu_s_per_episode"],
            cpu_s_learner=rows["vision"]["cpu_s_per_episode"],
            cpu_s_relabel=rows["relabel"]["cpu_s_per_log"],
            training_s=recorded_training_seconds(Path(run)) if run else None,
            nodes=cfg.nodes,
            cpus_per_node=workers,
        )
    return result


def recorded_training_seconds(run: Path) -> float | None:
    """The fit seconds a run folder's stage records hold (BC, DAgger rounds, perception with
    its frame rendering, vision fits): the work that stays on one machine."""
    stages = run / "stages"
    if not stages.is_dir():
        return None
    total = 0.0

    def walk(node: Any, key: str | None = None) -> None:
        nonlocal total
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, k)
        elif isinstance(node, list):
            for v in node:
                walk(v, key)
        elif key == "seconds" and isinstance(node, int | float):
            total += float(node)

    for path in sorted(stages.glob("*.json")):
        if path.stem in ("collect", "eval"):  # rollouts: priced from this bench
            continue
        walk(json.loads(path.read_text()))
    return total


def profile_episodes(p: Profile) -> dict[str, int]:
    """The episodes a full run of profile ``p`` flies, by kind (validation of every candidate
    included; the eval stage's Table 3 rows and its suite with the baseline model)."""
    suite_episodes = 0
    if p.eval_suite is not None:
        from training.provenance import REPO
        from training.suite import load_suite

        suite = load_suite(REPO / p.eval_suite)
        suite_episodes = sum(c.episodes or suite.episodes for c in suite.conditions)
        suite_episodes *= 2 if p.eval_suite_baseline else 1
    dagger_candidates = p.dagger_rounds + 1  # BC and each round
    vision_candidates = p.vision_rounds + 2  # the prior(s), vision BC, each round
    return {
        "expert": p.collect_episodes + p.eval_episodes,
        "learner": p.dagger_rounds * p.dagger_rollouts
        + p.vision_rounds * p.vision_rollouts
        + (dagger_candidates + vision_candidates) * p.validation_episodes
        + 3 * p.eval_episodes
        + suite_episodes,
        "relabel": p.dagger_rounds * p.dagger_rollouts + p.vision_rounds * p.vision_rollouts,
        "waves": 2 * p.dagger_rounds + 2 * p.vision_rounds + 6,
    }


def project_profile(
    p: Profile,
    cpu_s_expert: float,
    cpu_s_learner: float,
    cpu_s_relabel: float,
    training_s: float | None,
    nodes: tuple[int, ...],
    cpus_per_node: int,
) -> dict[str, Any]:
    """Wall time of profile ``p`` on ``n`` nodes of ``cpus_per_node`` CPUs each: the parallel
    CPU-seconds spread over every CPU, but no batch shorter than one episode per stage-step
    (``waves``: the sequential batches of a run — collect, each round's rollouts and
    relabelling, each validation, each evaluation), plus the serial training time."""
    eps = profile_episodes(p)
    parallel_cpu_s = (
        eps["expert"] * cpu_s_expert
        + eps["learner"] * cpu_s_learner
        + eps["relabel"] * cpu_s_relabel
    )
    longest = max(cpu_s_expert, cpu_s_learner)
    rows = {}
    for n in nodes:
        cpus = n * cpus_per_node
        parallel = max(parallel_cpu_s / cpus, eps["waves"] * longest)
        rows[str(n)] = {
            "cpus": cpus,
            "rollouts_min": parallel / 60.0,
            "total_min": (parallel + (training_s or 0.0)) / 60.0,
        }
    return {
        "profile": p.name,
        "episodes": eps,
        "parallel_cpu_s": parallel_cpu_s,
        "training_s": training_s,
        "nodes": rows,
    }


def format_rollout_bench(res: dict[str, Any]) -> str:
    lines = [
        f"rollouts: {res['episodes_per_kind']} episodes of each kind, local {res['workers']} "
        f"workers vs Ray {res['ray']} ({res['ray_cpus']} CPUs; started in "
        f"{res['ray_start_s']:.1f} s, not counted)"
    ]
    for kind in ("expert", "vision"):
        k = res["kinds"][kind]
        lines.append(
            f"  {kind:<8} local {k['local_episodes_per_min']:6.1f} ep/min   ray "
            f"{k['ray_episodes_per_min']:6.1f} ep/min   overhead {100 * k['ray_overhead']:5.1f} %"
            f"   ({k['cpu_s_per_episode']:.2f} CPU-s/episode)"
        )
    r = res["kinds"]["relabel"]
    lines.append(
        f"  relabel  local {r['local_logs_per_min']:6.1f} logs/min ray "
        f"{r['ray_logs_per_min']:6.1f} logs/min overhead {100 * r['ray_overhead']:5.1f} %   "
        f"({r['cpu_s_per_log']:.2f} CPU-s/log)"
    )
    lines.append(
        f"  all      local {res['local_s']:.1f} s, ray {res['ray_s']:.1f} s: overhead "
        f"{100 * res['ray_overhead']:.1f} %; logs identical: {res['logs_identical']}; "
        f"retried: {len(res['retried'])}"
    )
    proj = res.get("projection")
    if proj:
        e = proj["episodes"]
        train = proj["training_s"]
        lines.append(
            f"projection of profile {proj['profile']}: {e['expert']} expert + {e['learner']} "
            f"learner episodes, {e['relabel']} relabels = {proj['parallel_cpu_s'] / 3600:.1f} "
            "CPU-hours; training "
            + (f"{train / 60:.1f} min (recorded)" if train is not None else "not recorded")
        )
        for n, row in proj["nodes"].items():
            lines.append(
                f"  {n:>3} node(s), {row['cpus']:>4} CPUs: rollouts {row['rollouts_min']:6.1f} min"
                f", total {row['total_min']:6.1f} min"
            )
    return "\n".join(lines)
