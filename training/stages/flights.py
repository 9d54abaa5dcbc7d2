"""A run's flights: policy rollouts into ``flights/<folder>/`` (in process or through SITL +
companion processes), their offline expert labels in ``labels/<folder>/`` and the training
episodes loaded from both."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from training.dataset import Episode, load_episodes
from training.exec.rollout import RolloutSpec, completed_episode, log_name
from training.exec.transport import Transport
from training.profiles import PipelineError
from training.run_folder import Run
from training.stage_records import CollectRecord

__all__ = ["episodes", "expert_pairs", "fly", "relabel"]


def fly(
    run: Run,
    checkpoint: str,
    seed: int,
    count: int,
    folder: str,
    camera: bool,
    transport: str | None = None,
) -> list[Path]:
    """Rollouts of episodes ``0..count-1`` of ``seed`` with their flight logs in
    ``flights/<folder>/``; resumable (complete logs are not flown again). A run across worlds
    (``training.worlds``) splits ``count`` over them: world ``w`` flies its share of episodes
    on ``seed + w.seed_offset`` into ``flights/<folder>/<w.name>/``.

    ``transport`` (default: the profile's ``rollouts``): ``mavlink`` flies the policy
    through ``visland sitl`` + ``visland companion`` processes (``training.exec.fly_many``,
    lockstep, ``workers`` pairs) and returns the SITL's logs — the training record;
    ``inprocess`` flies the gymnasium env in ``workers`` processes."""
    transport = transport or run.profile.rollouts
    out: list[Path] = []
    for world, n in run.worlds.split(count):
        flights = run.root / "flights" / folder / world.name  # name "": a one-scenario run
        flights.mkdir(parents=True, exist_ok=True)
        wseed = seed + world.seed_offset
        if transport == Transport.MAVLINK:
            from training.exec.fly import sitl_log_name

            paths = [flights / sitl_log_name(wseed, i) for i in range(n)]
        else:
            paths = [flights / log_name(wseed, i) for i in range(n)]
        out += paths
        todo = [i for i, path in enumerate(paths) if not completed_episode(path)]
        if not todo:
            continue
        desc = f"fly {folder}{'/' + world.name if world.name else ''} ({transport})"
        with run.bar(len(todo), desc) as bar:
            if transport == Transport.MAVLINK:
                _fly_mavlink(run, checkpoint, wseed, todo, flights, camera, bar.update, world.file)
            else:
                spec = RolloutSpec(
                    policy=checkpoint,
                    seed=wseed,
                    scenario=world.file,
                    render_camera=camera,
                    log_dir=str(flights),
                )
                run.backend.episodes(spec, todo, lambda _: bar.update())
    return out


def _fly_mavlink(
    run: Run,
    checkpoint: str,
    seed: int,
    todo: list[int],
    flights: Path,
    camera: bool,
    progress: Callable[[int], Any],
    scenario: str | None,
) -> None:
    """SITL + companion pairs; a failed pair's episodes are flown once more, then a
    PipelineError names what failed (the logs that finished stay: a rerun resumes)."""
    from training.exec.fly import FlyConfig, FlyError, sitl_log_name
    from training.exec.fly_many import fly_many

    cfg = FlyConfig(
        policy=checkpoint,
        seed=seed,
        scenario=scenario,
        render=camera,
        out=str(flights / "mavlink"),
        sitl_log_dir=str(flights),
        progress=False,
    )
    for attempt in (1, 2):
        try:
            fly_many(cfg, todo, run.profile.workers, on_done=progress, backend=run.backend)
            return
        except FlyError as exc:
            todo = [i for i in todo if not completed_episode(flights / sitl_log_name(seed, i))]
            if attempt == 2:
                raise PipelineError(
                    f"{flights}: {len(todo)} SITL + companion rollouts failed twice "
                    f"(rerun to resume): {exc}"
                ) from None
            run.say(f"fly: {exc}\nflying the {len(todo)} missing episodes again")


def relabel(run: Run, logs: list[Path], folder: str) -> list[tuple[Path, Path]]:
    """Offline expert labels for learner logs (``expert.relabel``, as `visland relabel`)."""
    from expert.relabel import label_path

    out = run.root / "labels" / folder
    todo = [p for p in logs if not label_path(p, out).exists()]
    if todo:
        t0 = time.perf_counter()
        reports = run.backend.relabel(todo, out)
        bad = [r for r in reports if r.error]
        for r in bad:
            run.say(f"relabel: {r.error}")
        run.say(f"relabelled {len(todo)} logs in {time.perf_counter() - t0:.0f} s")
    return [(p, label_path(p, out)) for p in logs if label_path(p, out).exists()]


def episodes(run: Run, pairs: list[tuple[Path, Path | None]], images: bool) -> list[Episode]:
    """The training episodes of (log, labels) pairs; unreadable ones are skipped and said."""
    eps, errors = load_episodes(pairs, with_images=images, cache_dir=run.root / "cache")
    for e in errors:
        run.say(f"skipped: {e}")
    if not eps:
        raise PipelineError(f"{run.root}: no usable episodes ({len(errors)} unreadable)")
    return eps


def expert_pairs(run: Run) -> list[tuple[Path, Path | None]]:
    """The collect stage's expert flights (they carry their own commands: no labels)."""
    rec = run.need("collect", CollectRecord)
    return [(Path(p), None) for p in rec.logs]
