"""Execution backends: a local Ray instance flies, relabels and fails exactly as the local
backend does (same per-episode records, same log bytes), retries a worker killed mid-episode and
names work that fails twice."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest

from training.exec.backend import BackendError, LocalBackend
from training.exec.choose import check_ray_address
from training.exec.ray_backend import ray_available
from training.exec.rollout import RolloutSpec

pytestmark = pytest.mark.skipif(not ray_available(), reason="needs visland[ray]")


@pytest.fixture(scope="module")
def ray_backend():
    from training.exec.ray_backend import RayBackend

    backend = RayBackend("local", num_cpus=2, say=lambda _msg: None)
    try:
        yield backend
    finally:
        backend.close()


def _rows(outcomes):
    return [replace(o.row(), log=None) for o in outcomes]


def test_ray_gives_the_local_backends_records_logs_and_labels(tmp_path, ray_backend, low_scenario):
    local_dir, ray_dir = tmp_path / "local", tmp_path / "ray"
    spec = RolloutSpec(policy="expert", seed=41, scenario=low_scenario, render_camera=False)
    local = LocalBackend(2).episodes(
        RolloutSpec(**{**spec.__dict__, "log_dir": str(local_dir)}), [0, 1, 2, 3]
    )
    ray = ray_backend.episodes(
        RolloutSpec(**{**spec.__dict__, "log_dir": str(ray_dir)}), [0, 1, 2, 3]
    )
    assert [o.episode_index for o in ray] == [0, 1, 2, 3]
    assert _rows(ray) == _rows(local)
    assert all(o.result.landed for o in ray)
    for lo, ro in zip(local, ray, strict=True):
        assert Path(ro.log_path).parent == ray_dir
        assert Path(ro.log_path).name == Path(lo.log_path).name
        assert Path(ro.log_path).read_bytes() == Path(lo.log_path).read_bytes()
    assert not list(ray_dir.glob("*.part"))

    logs = sorted(local_dir.glob("*.mcap"))
    by_local = LocalBackend(2).relabel(logs, tmp_path / "labels_local")
    by_ray = ray_backend.relabel(logs, tmp_path / "labels_ray")
    assert [r.log for r in by_ray] == [str(p) for p in logs]
    assert all(r.error is None and r.steps > 0 for r in by_ray)
    assert [r.steps for r in by_ray] == [r.steps for r in by_local]
    for a, b in zip(by_local, by_ray, strict=True):
        assert Path(b.labels).parent == tmp_path / "labels_ray"
        assert Path(b.labels).read_bytes() == Path(a.labels).read_bytes()
    assert ray_backend.retried == []


def test_ray_relabel_reports_a_bad_log_and_labels_the_rest(tmp_path, ray_backend, low_scenario):
    spec = RolloutSpec(
        policy="expert", seed=42, scenario=low_scenario, render_camera=False, log_dir=str(tmp_path)
    )
    good = Path(ray_backend.episodes(spec, [0])[0].log_path)
    bad = tmp_path / "junk.mcap"
    bad.write_bytes(b"not an mcap file at all")
    reports = ray_backend.relabel([bad, good], tmp_path / "labels")
    assert reports[0].labels is None and str(bad) in reports[0].error
    assert reports[1].error is None and Path(reports[1].labels).exists()


def _descendants_titled(root_marker: str, title: str) -> list[int]:
    """PIDs of processes whose command line starts with ``title`` and whose parent's command
    line mentions ``root_marker`` (this test's own Ray instance's folder)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            ppid = int(
                next(
                    line.split()[1]
                    for line in (entry / "status").read_text().splitlines()
                    if line.startswith("PPid:")
                )
            )
            parent = Path(f"/proc/{ppid}/cmdline").read_bytes().decode(errors="replace")
        except (OSError, StopIteration, ValueError):
            continue
        if cmd.startswith(title) and root_marker in parent:
            found.append(int(entry.name))
    return found


def _fly_and_kill_one(backend, spec, indices):
    """Fly ``indices`` on ``backend`` while SIGKILLing the first worker seen flying an episode;
    returns (outcomes, killed PID or None)."""
    result: dict = {}

    def fly():
        try:
            result["ray"] = backend.episodes(spec, indices)
        except BaseException as exc:  # surfaced by the caller
            result["error"] = exc

    flying = threading.Thread(target=fly)
    flying.start()
    killed = None
    deadline = time.monotonic() + 120
    while killed is None and flying.is_alive() and time.monotonic() < deadline:
        pids = _descendants_titled(backend._tmp, "ray::_episode_task")
        if pids:  # its title says it is flying an episode now
            os.kill(pids[0], signal.SIGKILL)
            killed = pids[0]
        time.sleep(0.05)
    flying.join(300)
    assert "error" not in result, result.get("error")
    return result["ray"], killed


def test_ray_retries_an_episode_whose_worker_is_killed(tmp_path, ray_backend):
    """A worker killed mid-episode (as when a node is lost): the episode flies again, the
    backend names it, and the records are the local backend's."""
    spec = RolloutSpec(policy="expert", seed=43, render_camera=True, log_dir=str(tmp_path / "r"))
    # the kill can land just after an episode ended (the worker then idles): try a fresh pair
    for first in (0, 2, 4):
        indices = [first, first + 1]
        outcomes, killed = _fly_and_kill_one(ray_backend, spec, indices)
        assert killed is not None, "no episode worker of this test's Ray instance was seen"
        if ray_backend.retried:
            break
    assert len(ray_backend.retried) == 1, ray_backend.retried
    assert ray_backend.retried[0] in {f"episode {i} of seed 43" for i in indices}
    local = LocalBackend(1).episodes(
        RolloutSpec(**{**spec.__dict__, "log_dir": str(tmp_path / "l")}), indices
    )
    assert _rows(outcomes) == _rows(local)
    for lo, ro in zip(local, outcomes, strict=True):
        assert Path(ro.log_path).read_bytes() == Path(lo.log_path).read_bytes()
    ray_backend.retried.clear()


def test_ray_names_episodes_that_fail_twice(tmp_path, ray_backend):
    ckpt = tmp_path / "broken.pt"
    ckpt.write_bytes(b"\x00 not a checkpoint")
    spec = RolloutSpec(policy=str(ckpt), seed=44, render_camera=False)
    with pytest.raises(BackendError) as err:
        ray_backend.episodes(spec, [0, 1])
    text = str(err.value)
    assert "2 of 2 episodes failed" in text
    assert "episode 0 of seed 44: failed twice" in text
    assert "episode 1 of seed 44: failed twice" in text
    assert sorted(ray_backend.retried) == ["episode 0 of seed 44", "episode 1 of seed 44"]
    ray_backend.retried.clear()


@pytest.mark.parametrize("address", ["auto", "local", "ray://head:10001", "10.1.2.3:6379"])
def test_ray_addresses_accepted(address):
    assert check_ray_address(address) == address


def test_bad_ray_address_is_a_clear_cli_error():
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", "eval", "--ray", "my cluster", "--episodes", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "--ray 'my cluster': expected auto" in proc.stderr


def test_shared_dir_without_ray_is_refused():
    from training.exec.choose import open_backend

    with pytest.raises(ValueError, match="--shared-dir is for --ray"):
        open_backend(None, 1, "/tmp")


def test_ray_flies_sitl_companion_pairs_as_the_local_backend(tmp_path, ray_backend, low_scenario):
    """``fly --instances`` on Ray: each run is one SITL + companion pair on its node's own ports;
    the SITL logs come back under the driver's folder and the records are the local ones."""
    from training.exec.fly import FlyConfig
    from training.exec.fly_many import fly_many

    # equal records need every frame answered: a loaded machine must not let the SITL's 0.5 s
    # lockstep wait lapse in one run and not in the other (a patient wait, as other tests use)
    cfg = FlyConfig(
        policy="expert",
        seed=48,
        scenario=low_scenario,
        progress=False,
        sitl_args=("--lockstep-timeout-s", "5"),
    )
    local = fly_many(replace(cfg, out=str(tmp_path / "l")), [0, 1, 2], instances=2, chunk=2)
    ray = fly_many(replace(cfg, out=str(tmp_path / "r")), [0, 1, 2], chunk=2, backend=ray_backend)
    assert ray.backend.name == "ray" and ray.runs == 2
    assert [replace(r, log=None) for r in ray.per_episode] == [
        replace(r, log=None) for r in local.per_episode
    ]
    for row in ray.per_episode:
        assert Path(row.log).parent == tmp_path / "r" / "sitl" and Path(row.log).is_file()
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["ep0000", "ep0002", "sitl"]
    assert list((tmp_path / "r" / "ep0000" / "companion").glob("*.mcap"))


def test_an_unreachable_cluster_is_a_clear_error_at_once():
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    cmd = [sys.executable, "-m", "tools.cli", "eval", "--episodes", "1", "--no-camera"]
    proc = subprocess.run(
        [*cmd, "--ray", f"127.0.0.1:{port}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1, proc.stderr
    assert f"cannot reach 127.0.0.1:{port}" in proc.stderr
    assert f"ray start --head --port {port}" in proc.stderr
    assert time.monotonic() - t0 < 100  # not Ray's minutes of retrying
