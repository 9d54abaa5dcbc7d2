"""The companion installs on a board by itself: the wheel ``make wheel`` builds, installed as
``'<wheel>[companion]'`` in a fresh venv, gives a working ``visland companion`` with no torch,
pybullet, cvxpy or scipy, carrying the shipped model (checkpoint + ONNX graphs) and the hardware
config template as package data; run from a folder outside the checkout it flies that model
(ONNX Runtime) against the SITL of the full venv.

The wheel is built by ``make wheel`` in a copy of the tracked files (a fresh clone's: no stale
``build/`` leftovers), with this venv's pip and setuptools; the fresh venv's dependencies come
from the package index pip is configured with (the only network this test uses besides
loopback). The wheel's contents are checked without installing it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

from companion.packaged import MODEL_FILES, TEMPLATE
from training.exec.fly import FlyConfig, fly

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models" / "visland_vision.pt"
MAKE_WHEEL = ("make", "wheel", f"BIN={Path(sys.executable).parent}", "-o", ".venv/.installed")
"""``make wheel`` with this venv's tools (``-o``: the copy has no venv of its own to set up)."""
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
def wheel(tmp_path_factory) -> Path:
    """The wheel ``make wheel`` builds from a fresh clone's files."""
    src = tmp_path_factory.mktemp("build") / "src"
    _tracked_copy(src)
    _run(["make", "-C", str(src), *MAKE_WHEEL[1:]], timeout=300)
    (built,) = (src / "dist").glob("visland-*.whl")
    return built


def test_the_wheel_carries_the_shipped_model_and_the_hardware_template(wheel):
    with zipfile.ZipFile(wheel) as whl:
        names = set(whl.namelist())
        for name in (*MODEL_FILES, TEMPLATE):
            member = f"companion/assets/{name}"
            assert member in names, f"{wheel.name}: no {member}"
            assert whl.read(member) == (REPO / "companion" / "assets" / name).read_bytes()
    assert {n.split("/")[0] for n in names} >= {"companion", "tools", "training"}


@pytest.fixture(scope="module")
def board_venv(wheel, tmp_path_factory) -> Path:
    """A fresh venv with ``visland[companion]`` installed from the freshly built wheel."""
    env_dir = tmp_path_factory.mktemp("install") / "venv"
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


def test_board_install_flies_its_packaged_model_against_the_sitl(board_venv, tmp_path):
    """One lockstep landing: the SITL in this (full) venv, the companion from the board venv,
    run in a folder outside the checkout, on the model its package carries, on ONNX Runtime
    (``--runtime auto`` picks it: the export is beside the checkpoint)."""
    py, visland = board_venv / "bin" / "python", board_venv / "bin" / "visland"
    probe = "import companion.packaged as p; print(p.shipped_policy()); print(p.template())"
    model, config = map(Path, _run([str(py), "-I", "-c", probe]).stdout.split())
    assert model.is_relative_to(board_venv) and config.parent == model.parent
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    report = fly(
        FlyConfig(
            policy=str(model),
            episodes=1,
            out=str(tmp_path / "fly"),
            companion_command=(str(py), "-I", str(visland), "companion"),
            companion_cwd=str(elsewhere),
            progress=False,
        )
    )
    assert report.episodes == 1 and report.summary.success_rate == 1.0, report
    assert report.per_episode[0].landing_error_m < 0.5
    log = (tmp_path / "fly" / "companion.log").read_text()
    assert f"policy {model}: runtime onnx (auto)" in log, log[-2000:]


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
