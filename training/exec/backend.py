"""Where a command's many episodes fly: the execution backends.

Every command that flies many episodes (``collect``, ``eval``, ``eval --suite``, ``relabel``,
``fly --instances`` and the pipeline's rollouts, validation and evaluation) hands its work to a
:class:`Backend`, which has three kinds of work:

* :meth:`Backend.episodes` — in-process episodes of one :class:`~training.exec.rollout.RolloutSpec`
  (their flight logs, if any, into ``spec.log_dir``);
* :meth:`Backend.relabel` — offline expert labels of flight logs (``expert.relabel``);
* :meth:`Backend.fly_runs` — runs of consecutive episodes, each through one SITL + companion
  pair in lockstep (``training.exec.fly.fly_run``).

A backend runs the tasks it is handed (``training.exec.rollout``, ``training.exec.fly``,
``expert.relabel``) and imports none of its callers: ``training.exec.fly_many``, the
evaluation and the pipeline import it, never the other way round. Which backend a command gets
(``--ray``, ``--shared-dir``) is ``training.exec.choose``.

Two implementations: :class:`LocalBackend` (the default: this host's spawn process pool and
SITL + companion pairs side by side; no Ray needed) and
``training.exec.ray_backend.RayBackend`` (``--ray ADDRESS``; the optional extra
``visland[ray]``). Both give the same per-episode records and the same log files (names and
bytes) for the same seeds, because every episode depends only on (seed, index) and in-process
logs and labels are written reproducibly (``FlightLogWriter(reproducible=True)``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from expert.relabel import RelabelReport
    from training.exec.fly import FlyConfig
    from training.exec.rollout import EpisodeOutcome, RolloutSpec
    from training.reports import FlyReport

__all__ = ["Backend", "BackendError", "LocalBackend"]


class BackendError(RuntimeError):
    """Work that could not be done (names each episode, log or run; what finished is kept)."""


class Backend(ABC):
    """Flies a command's episodes; use as a context manager (:meth:`close` at the end)."""

    name: str = ""

    def __init__(self) -> None:
        self.retried: list[str] = []
        """What had to be done a second time (e.g. ``episode 3 of seed 7``), in order."""

    @abstractmethod
    def episodes(
        self,
        spec: RolloutSpec,
        indices: list[int],
        on_done: Callable[[EpisodeOutcome], None] | None = None,
    ) -> list[EpisodeOutcome]:
        """Fly episodes ``indices`` of ``spec.seed``; outcomes sorted by index, logs (when
        ``spec.log_dir``) in ``spec.log_dir`` under :func:`training.exec.rollout.log_name`."""

    @abstractmethod
    def relabel(
        self,
        logs: list[Path],
        out_dir: Path,
        on_done: Callable[[RelabelReport], None] | None = None,
    ) -> list[RelabelReport]:
        """Expert labels of each log into ``out_dir``; a log that cannot be labelled is
        reported (``error``) and the rest go on. Reports in the order of ``logs``."""

    @abstractmethod
    def fly_runs(
        self,
        cfg: FlyConfig,
        runs: list[tuple[int, int]],
        out: Path,
        sitl_dir: Path,
        on_done: Callable[[int], None] | None = None,
    ) -> tuple[list[FlyReport], list[str]]:
        """Each ``(first, count)`` run through one SITL + companion pair
        (:func:`training.exec.fly.fly_run`: the pair's files in ``out/ep<first>/``, the SITL's
        flight logs in ``sitl_dir``). Returns the reports of the runs that finished and one
        line per run that failed. ``on_done(count)`` after each finished run."""

    @property
    def slots(self) -> int:
        """How many episodes fly at once (the local workers, or the cluster's CPUs)."""
        return 1

    def describe(self) -> dict[str, Any]:
        """What the run was flown on, for reports (``retried`` included)."""
        return {"name": self.name, "slots": self.slots, "retried": list(self.retried)}

    def close(self) -> None:  # noqa: B027 - a backend with nothing to release keeps this
        """Release what the backend holds (a Ray connection, a local Ray instance)."""

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LocalBackend(Backend):
    """This host: ``workers`` spawn processes for in-process episodes and relabelling,
    ``workers`` SITL + companion pairs side by side for MAVLink runs."""

    name = "local"

    def __init__(self, workers: int = 1) -> None:
        super().__init__()
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers

    @property
    def slots(self) -> int:
        return self.workers

    # the tasks load the simulator, the expert and torch: imported when there is work, so
    # that a command's parser (``training.exec.choose``) stays light
    def episodes(self, spec, indices, on_done=None):
        from training.exec.rollout import run_episodes

        return run_episodes(spec, indices, self.workers, on_done)

    def relabel(self, logs, out_dir, on_done=None):
        from expert.relabel import relabel

        return relabel(logs, out_dir, workers=self.workers, on_done=on_done)

    def fly_runs(self, cfg, runs, out, sitl_dir, on_done=None):
        from training.exec.fly import FlyError, fly_run

        reports, failures = [], []
        with ThreadPoolExecutor(max_workers=min(self.workers, len(runs))) as pool:
            futures = {
                pool.submit(fly_run, cfg, first, n, out, sitl_dir): (first, n) for first, n in runs
            }
            for future in as_completed(futures):
                first, n = futures[future]
                try:
                    reports.append(future.result())
                except FlyError as exc:
                    failures.append(f"episodes {first}..{first + n - 1}: {exc}")
                    continue
                if on_done is not None:
                    on_done(n)
        return reports, failures
