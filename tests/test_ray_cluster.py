"""Opt-in (slow): a real two-node Ray cluster on loopback — ``ray start --head`` and a second
``ray start --address`` with one CPU each, token authentication on — flies ``visland eval`` and
``visland collect`` with the same records and log bytes as the local backend; both nodes are
stopped by PID (and anything left in the cluster's own temp folder), even on failure.

The nodes register 127.0.0.2, not 127.0.0.1: Ray replaces 127.0.0.1 / localhost by the host's
network address (so that other machines could reach it); any other loopback address it keeps,
so every packet of the test stays on loopback."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from training.exec.ray_backend import ray_available
from training.provenance import REPO

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not ray_available(), reason="needs visland[ray]"),
]

RAY = Path(sys.executable).parent / "ray"


LOOPBACK = "127.0.0.2"


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


def _alive_nodes(address: str, env: dict[str, str]) -> int:
    code = (
        f"import ray; ray.init(address={address!r}, logging_level='ERROR'); "
        "print(sum(1 for n in ray.nodes() if n['Alive'])); ray.shutdown()"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    return int(proc.stdout.strip().splitlines()[-1]) if proc.returncode == 0 else 0


def _ours(marker: str) -> list[int]:
    """PIDs whose command line names this cluster's temp folder."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if marker in (entry / "cmdline").read_bytes().decode(errors="replace"):
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


@pytest.fixture
def cluster():
    tmp = tempfile.mkdtemp(prefix="vrc_", dir="/tmp")  # short: Ray's socket paths
    port = _free_tcp_port()
    address = f"{LOOPBACK}:{port}"
    env = {
        **os.environ,
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN": secrets.token_hex(32),
        "RAY_USAGE_STATS_ENABLED": "0",
    }
    common = ["--num-cpus", "1", "--temp-dir", tmp, "--node-ip-address", LOOPBACK]
    common += ["--block", "--disable-usage-stats"]
    head_only = ["--include-dashboard=false"]
    nodes: list[subprocess.Popen] = []
    try:
        with open(Path(tmp) / "head.out", "w") as out:
            nodes.append(
                subprocess.Popen(
                    [str(RAY), "start", "--head", "--port", str(port), *head_only, *common],
                    env=env,
                    stdout=out,
                    stderr=subprocess.STDOUT,
                )
            )
        deadline = time.monotonic() + 120
        while _alive_nodes(address, env) < 1:
            assert time.monotonic() < deadline, (Path(tmp) / "head.out").read_text()[-2000:]
            time.sleep(1)
        with open(Path(tmp) / "worker.out", "w") as out:
            nodes.append(
                subprocess.Popen(
                    [str(RAY), "start", "--address", address, *common],
                    env=env,
                    stdout=out,
                    stderr=subprocess.STDOUT,
                )
            )
        while _alive_nodes(address, env) < 2:
            assert time.monotonic() < deadline, (Path(tmp) / "worker.out").read_text()[-2000:]
            time.sleep(1)
        yield address, env
    finally:
        for node in reversed(nodes):  # `ray start --block` stops its node's processes
            node.send_signal(signal.SIGTERM)
            try:
                node.wait(60)
            except subprocess.TimeoutExpired:
                node.kill()
                node.wait(10)
        for pid in _ours(tmp):  # anything of this cluster still running
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        shutil.rmtree(tmp, ignore_errors=True)


def _visland(*args: str, env: dict[str, str] | None = None) -> tuple[dict, str]:
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", *args, "--json"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout), proc.stderr


def test_two_node_cluster_flies_what_the_local_backend_flies(cluster, tmp_path):
    address, env = cluster
    common = ["--policy", "expert", "--episodes", "6", "--seed", "46", "--no-camera"]
    local, _ = _visland("eval", *common, "--workers", "2")
    ray, said = _visland("eval", *common, "--ray", address, env=env)
    assert "2 node(s), 2 CPUs" in said
    assert ray["backend"]["name"] == "ray" and ray["backend"]["retried"] == []
    assert ray["per_episode"] == local["per_episode"]

    on_ray, _ = _visland(
        "collect", "--out", str(tmp_path / "ray"), "--episodes", "3", "--seed", "47",
        "--ray", address, env=env,
    )  # fmt: skip
    _visland("collect", "--out", str(tmp_path / "local"), "--episodes", "3", "--seed", "47")
    assert on_ray["flown_now"] == 3
    for log in sorted((tmp_path / "local" / "flights").glob("*.mcap")):
        assert (tmp_path / "ray" / "flights" / log.name).read_bytes() == log.read_bytes()
