"""The Ray backend with ``--shared-dir`` (logs travel through a folder every node mounts) and
as the pipeline's backend: the same flight logs and labels as the local backend, and the shared
folder left empty."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from training.exec.backend import LocalBackend
from training.exec.ray_backend import ray_available
from training.pipeline import run_pipeline
from training.profiles import PROFILES

pytestmark = pytest.mark.skipif(not ray_available(), reason="needs visland[ray]")


def test_pipeline_stages_on_ray_through_a_shared_dir_match_the_local_backend(tmp_path):
    from training.exec.ray_backend import RayBackend

    profile = replace(
        PROFILES["quick"], collect_episodes=4, dagger_rollouts=3, rollouts="inprocess"
    )
    shared = tmp_path / "shared"
    with RayBackend("local", num_cpus=2, shared_dir=shared, say=lambda _m: None) as ray:
        on_ray = run_pipeline(
            tmp_path / "ray", profile, stages=("collect",), progress=False, backend=ray
        )
        ray_logs = [Path(p) for p in on_ray["collect"]["logs"]]
        labels = ray.relabel(ray_logs, tmp_path / "ray" / "labels")
        assert ray.retried == []
        assert not any(p.is_file() for p in ray.shared.rglob("*"))  # everything moved out
    assert not shared.exists() or not any(shared.iterdir())  # the command's folder removed
    local = run_pipeline(
        tmp_path / "local", profile, stages=("collect",), progress=False, backend=LocalBackend(2)
    )
    local_logs = [Path(p) for p in local["collect"]["logs"]]
    assert [p.name for p in ray_logs] == [p.name for p in local_logs]
    for a, b in zip(local_logs, ray_logs, strict=True):
        assert a.read_bytes() == b.read_bytes()
    local_labels = LocalBackend(2).relabel(local_logs, tmp_path / "local" / "labels")
    for a, b in zip(local_labels, labels, strict=True):
        assert b.error is None
        assert Path(a.labels).read_bytes() == Path(b.labels).read_bytes()
