"""Stage ``collect``: the expert's flights with camera, in process, into ``flights/expert/``."""

from __future__ import annotations

import time

from training.exec.transport import Transport
from training.run_folder import Run
from training.stage_records import CollectRecord
from training.stages.flights import fly

__all__ = ["run"]


def run(r: Run) -> CollectRecord:
    p = r.profile
    t0 = time.perf_counter()
    logs = fly(
        r,
        "expert",
        p.collect_seed,
        p.collect_episodes,
        "expert",
        True,
        transport=Transport.INPROCESS,
    )
    return r.finish(
        CollectRecord(
            stage="collect",
            git_commit=r.commit,
            logs=tuple(str(x) for x in logs),
            seed=p.collect_seed,
            seconds=time.perf_counter() - t0,
        )
    )
