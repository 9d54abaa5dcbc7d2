"""The companion installs on a board by itself: ``pip install 'visland[companion]'`` in a fresh
venv gives a working ``visland companion`` with no torch, pybullet, cvxpy or scipy, and it flies
the shipped model (ONNX Runtime, the graphs in ``models/``) against the SITL of the full venv.

The wheel is built from a copy of the tracked files (no stale ``build/`` leftovers), without
build isolation (setuptools is in the dev venv); the fresh venv's dependencies come from the
package index pip is configured with (the only network this test uses besides loopback).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

from training.exec.fly import FlyConfig, fly

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models" / "visland_vision.pt"
_PIP_WHEEL = (sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q")
_PIP_INSTALL = ("-m", "pip", "install", "-q", "--retries", "5", "--disable-pip-version-check")
ABSENT = ("torch", "pybullet", "cvxpy", "scipy", "gymnasium", "matplotlib")


def _tracked_copy(dest: Path) -> None:
    """The files git tracks (a fresh clone's), copied to ``dest``."""
    files = subprocess.run(
        ["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True
    ).stdout.split(b"\0")
    for name in filter(None, files):
        src = REPO / name.decode()
        if src.is_file():
            (dest / name.decode()).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name.decode())


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, **kw)
    assert res.returncode == 0, f"{cmd}: exit {res.returncode}\n{res.stdout}\n{res.stderr}"
    return res


@pytest.fixture(scope="module")
def board_venv(tmp_path_factory) -> Path:
    """A fresh venv with ``visland[companion]`` installed from a freshly built wheel."""
    root = tmp_path_factory.mktemp("install")
    src, dist, env_dir = root / "src", root / "dist", root / "venv"
    _tracked_copy(src)
    _run(
        [*_PIP_WHEEL, "-w", str(dist), str(src)],
        timeout=300,
    )
    (wheel,) = dist.glob("visland-*.whl")
    venv.EnvBuilder(with_pip=True).create(env_dir)
    _run(
        [str(env_dir / "bin" / "python"), *_PIP_INSTALL, f"{wheel}[companion]"],
        timeout=600,
    )
    return env_dir


def test_companion_extra_installs_without_torch_sim_or_solvers(board_venv):
    py = str(board_venv / "bin" / "python")
    probe = (
        "import importlib.util, json, companion; "
        f"print(json.dumps({{m: importlib.util.find_spec(m) is not None for m in {ABSENT!r}}}));"
        "print(companion.__file__)"
    )
    lines = _run([py, "-I", "-c", probe]).stdout.splitlines()
    assert json.loads(lines[0]) == dict.fromkeys(ABSENT, False)
    assert lines[1].startswith(str(board_venv))  # the installed package, not this checkout
    for module in ABSENT[:3]:
        res = subprocess.run([py, "-I", "-c", f"import {module}"], capture_output=True)
        assert res.returncode != 0
    # the installed companion answers; a command that needs the simulator names its extra
    assert (
        "--runtime"
        in _run([py, "-I", str(board_venv / "bin" / "visland"), "companion", "-h"]).stdout
    )
    res = subprocess.run(
        [py, "-I", str(board_venv / "bin" / "visland"), "sitl", "--episodes", "1"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2
    assert "needs the 'sim' extra" in res.stderr and "pip install 'visland[sim]'" in res.stderr


def test_board_install_flies_the_shipped_model_against_the_sitl(board_venv, tmp_path):
    """One lockstep landing: the SITL in this (full) venv, the companion from the board venv on
    ONNX Runtime (``--runtime auto`` picks it: the export is beside the shipped checkpoint)."""
    py, visland = board_venv / "bin" / "python", board_venv / "bin" / "visland"
    report = fly(
        FlyConfig(
            policy=str(SHIPPED),
            episodes=1,
            out=str(tmp_path / "fly"),
            companion_command=(str(py), "-I", str(visland), "companion"),
            progress=False,
        )
    )
    assert report["episodes"] == 1 and report["success_rate"] == 1.0, report
    assert report["per_episode"][0]["landing_error_m"] < 0.5
    log = (tmp_path / "fly" / "companion.log").read_text()
    assert "runtime onnx (auto)" in log, log[-2000:]


def test_board_install_benches_the_onnx_policy_without_torch(board_venv):
    """`visland bench policy --runtime onnx` on the board times the export the companion flies
    (no torch to export or compare with); `--runtime torch` names the extra it needs."""
    py, visland = str(board_venv / "bin" / "python"), str(board_venv / "bin" / "visland")
    argv = [py, "-I", visland, "bench", "policy", "--checkpoint", str(SHIPPED)]
    res = json.loads(_run([*argv, "--runtime", "onnx", "--json"], timeout=120).stdout)
    assert set(res) == {"checkpoint", "steps", "threads", "onnx_alone"}
    alone = res["onnx_alone"]
    assert alone["kind"] == "vision" and 0 < alone["median_ms"] <= alone["p99_ms"]
    res = subprocess.run([*argv, "--runtime", "torch"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert "needs the 'torch' extra" in res.stderr, res.stderr
