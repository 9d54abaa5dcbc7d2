"""The ONNX Runtime backend of the companion (``runtime = "onnx"``, the ``onnx`` extra).

The shipped model is exported (beside a copy, in a temporary folder), flown through the real
companion process with ``--runtime onnx`` over MAVLink, and its log replayed through the torch
backend: torch gives back the commands ONNX Runtime flew within 1e-5 (the two backends differ
only in the CNN's float32 summation order, ~1e-6). A broken, stale or missing export, and a
missing onnxruntime, are each refused with the file and the fix named.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.onnx_export import export_onnx
from companion.onnx_runtime import OnnxModelError, OnnxPolicy, onnx_paths
from companion.policy_net import LearnedPolicy, PolicyCore, save_checkpoint, untrained_policy
from companion.runtime import PolicyRuntime, load_policy_file, resolve_runtime

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models" / "visland_vision.pt"

needs_onnx = pytest.mark.skipif(
    importlib.util.find_spec("onnxruntime") is None or importlib.util.find_spec("onnx") is None,
    reason="the onnx extra: pip install 'visland[onnx]'",
)


@pytest.fixture(scope="module")
def shipped(tmp_path_factory) -> Path:
    """A copy of the shipped checkpoint with its ONNX export beside it."""
    ckpt = tmp_path_factory.mktemp("onnx") / SHIPPED.name
    shutil.copyfile(SHIPPED, ckpt)
    export_onnx(ckpt)
    return ckpt


@needs_onnx
def test_export_writes_two_checked_graphs_beside_the_checkpoint(tmp_path):
    net = untrained_policy(seed=4)
    ckpt = save_checkpoint(tmp_path / "net.pt", net.config, net.control, net.perception, {})
    res = export_onnx(ckpt, check_samples=32)
    perception, control = onnx_paths(ckpt)
    assert res.perception == str(perception) and res.control == str(control)
    assert perception.stat().st_size > 10_000 and control.stat().st_size > 10_000
    assert res.perception_max_rel_diff <= 1e-5 and res.control_max_abs_diff <= 1e-5
    # the policy built on the graphs shares LearnedPolicy's core: same estimator, same act();
    # its config and metadata come from the graphs' metadata, not from unpickling the .pt
    onnx_policy = load_policy_file(ckpt, 1, "onnx")
    assert isinstance(onnx_policy, PolicyCore) and not isinstance(onnx_policy, LearnedPolicy)
    assert onnx_policy.metadata["runtime"] == "onnx"
    assert onnx_policy.config == net.config
    # a privileged checkpoint has no CNN: one graph, and a stale CNN file is removed
    priv = untrained_policy(seed=5, privileged=True)
    save_checkpoint(ckpt, priv.config, priv.control, None, {})
    res = export_onnx(ckpt, check_samples=8)
    assert res.perception is None and not perception.exists() and control.exists()
    assert load_policy_file(ckpt, 1, "onnx").privileged


@needs_onnx
def test_shipped_model_onnx_flies_the_companion_and_torch_reproduces_it(shipped, low_scenario):
    """``visland bench companion --runtime onnx`` on one low flight: the real companion flies
    ONNX Runtime over MAVLink; its recorded frames and telemetry, replayed through torch and
    through ONNX Runtime, give the flown commands back; the bench prints both step times."""
    from tools.bench_companion import bench_companion, format_bench

    res = bench_companion(
        policy=str(shipped),
        episodes=1,
        seed=0,
        scenario=low_scenario,
        runtime="onnx",
        scene_baseline=True,
    )
    assert res["runtime"] == "onnx" and res["commands"] > 20
    assert 0 < res["median_ms"] < 50 and res["p99_ms"] >= res["median_ms"]
    cmp = res["compare"]
    assert cmp["torch"]["steps"] == cmp["onnx"]["steps"] == res["commands"]
    assert cmp["onnx"]["max_abs_diff_vs_flown"] <= 1e-9  # its own log: deterministic
    assert cmp["torch"]["max_abs_diff_vs_flown"] <= 1e-5  # the other backend
    assert cmp["onnx_speedup"] > 0
    # --scene-baseline: the same flight with --log-scene off; its log has no scene, ours has
    plain = res["scene_off"]
    assert plain["success_rate"] == res["success_rate"]
    # the flight ends at touchdown, which the companion's last setpoint may cross by one frame
    # on a busy machine (74 vs 75 commands seen under load)
    assert abs(plain["commands"] - res["commands"]) <= 2
    # (the ratio of log bytes is a figure, not a property: how much telemetry a loaded machine
    # streams besides the lockstep frames varies; the channels below are what the option does)
    assert res["scene_vs_off"]["log_bytes_per_flight"] > 0
    run = Path(res["run"])
    (with_scene,) = read_log_topics(run / "fly" / "companion")
    (without,) = read_log_topics(run / "scene_off" / "companion")
    assert with_scene["/scene"] == res["commands"] and "/scene" not in without
    text = format_bench(res)
    assert "frame receipt -> setpoint sent (runtime onnx" in text and "onnx median" in text
    assert "with --log-scene off" in text


def read_log_topics(folder: Path) -> list[dict[str, int]]:
    """topic -> message count of each companion log in ``folder``."""
    from companion.flightlog import read_log

    out = []
    for path in sorted(folder.glob("*.mcap")):
        log = read_log(path)
        out.append({**{t: len(v) for t, v in log.messages.items()}, **log.binary})
    return out


@needs_onnx
def test_torch_and_onnx_agree_step_by_step_on_the_shipped_model(shipped):
    """Rendered-like inputs without a flight: 200 steps of random images and sensors."""
    torch_p = load_policy_file(shipped, 1, "torch")
    onnx_p = load_policy_file(shipped, 1, "onnx")
    from training.bench_policy import _observation

    rng = np.random.default_rng(1)
    a, b = PolicyRuntime(torch_p, "torch"), PolicyRuntime(onnx_p, "onnx")
    worst = 0.0
    for i in range(200):
        obs = _observation(rng, i)
        ra, rb = a.step(obs, None), b.step(obs, None)
        assert ra.error is None and rb.error is None
        ca = np.r_[ra.command.thrust_norm, ra.command.rate_frd_rad_s]
        cb = np.r_[rb.command.thrust_norm, rb.command.rate_frd_rad_s]
        worst = max(worst, float(np.max(np.abs(ca - cb))))
    assert worst <= 1e-4, worst  # random jumps of range/attitude: the loosest case


@needs_onnx
def test_broken_stale_or_missing_exports_are_refused_with_the_fix(shipped, tmp_path):
    ckpt = tmp_path / "p.pt"
    shutil.copyfile(shipped, ckpt)
    perception, control = onnx_paths(ckpt)
    with pytest.raises(OnnxModelError, match=r"p\.control\.onnx: no such ONNX file.*export-onnx"):
        load_policy_file(ckpt, 1, "onnx")
    for src, dst in zip(onnx_paths(shipped), (perception, control), strict=True):
        shutil.copyfile(src, dst)
    assert load_policy_file(ckpt, 1, "onnx").config.kind == "vision"  # same bytes: accepted
    # corrupt: truncated protobuf
    data = control.read_bytes()
    control.write_bytes(data[: len(data) // 2])
    with pytest.raises(OnnxModelError, match=r"p\.control\.onnx: not a loadable ONNX model"):
        load_policy_file(ckpt, 1, "onnx")
    # the CNN graph where the LSTM step should be
    shutil.copyfile(perception, control)
    with pytest.raises(OnnxModelError, match=r"not a visland control export.*'perception'"):
        load_policy_file(ckpt, 1, "onnx")
    # a retrained checkpoint with the old export beside it
    shutil.copyfile(onnx_paths(shipped)[1], control)
    net = untrained_policy(seed=9)
    save_checkpoint(ckpt, net.config, net.control, net.perception, {})
    with pytest.raises(OnnxModelError, match=r"another checkpoint.*stale export.*export-onnx"):
        load_policy_file(ckpt, 1, "onnx")
    with pytest.raises(ValueError, match=r"runtime = 'tensorrt'; expected one of"):
        load_policy_file(ckpt, 1, "tensorrt")


def test_without_onnxruntime_the_error_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # `import onnxruntime` fails
    with pytest.raises(OnnxModelError, match=r"needs onnxruntime: pip install 'visland\[onnx\]'"):
        load_policy_file(SHIPPED, 1, "onnx")
    with pytest.raises(OnnxModelError, match=r"needs onnxruntime.*visland\[train\]"):
        export_onnx(SHIPPED)
    # auto: without onnxruntime the checkpoint flies on torch, export or not
    assert resolve_runtime(SHIPPED, "auto") == "torch"


@needs_onnx
def test_auto_runtime_is_onnx_where_the_export_is(shipped, tmp_path):
    assert resolve_runtime(shipped, "auto") == "onnx"  # the fixture exported it
    bare = tmp_path / "bare.pt"
    shutil.copyfile(shipped, bare)
    assert resolve_runtime(bare, "auto") == "torch"
    assert resolve_runtime(bare, "onnx") == "onnx"  # explicit: then refused at load if missing
    assert isinstance(load_policy_file(shipped, 1), OnnxPolicy)
    assert isinstance(load_policy_file(bare, 1), LearnedPolicy)


@needs_onnx
def test_cli_export_and_companion_runtime_errors(shipped, tmp_path, capsys):
    """In process (``tools.cli.main``): what a user types, its output and exit code."""
    from tools.cli import main

    ckpt = tmp_path / "c.pt"
    shutil.copyfile(shipped, ckpt)
    assert main(["export-onnx", "--checkpoint", str(ckpt), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["control"] == str(onnx_paths(ckpt)[1]) and res["perception_max_rel_diff"] <= 1e-5
    assert main(["export-onnx", "--checkpoint", str(tmp_path / "none.pt")]) == 2
    assert "none.pt: no such checkpoint file" in capsys.readouterr().err
    # the companion refuses before opening any port (here: a replay), naming the broken graph
    onnx_paths(ckpt)[0].write_bytes(b"\x00" * 64)
    argv = ["companion", "--policy", str(ckpt), "--runtime", "onnx", "--replay", "x.mcap"]
    assert main(argv) == 2
    assert "c.perception.onnx: not a loadable ONNX model" in capsys.readouterr().err
    argv = ["companion", "--policy", "untrained", "--runtime", "onnx", "--replay", "x.mcap"]
    assert main(argv) == 2
    assert "needs a checkpoint file" in capsys.readouterr().err
    assert main(["bench", "companion", "--checkpoint", str(tmp_path / "none.pt")]) == 2
    assert "none.pt: no such checkpoint file" in capsys.readouterr().err


@needs_onnx
def test_bench_policy_times_onnx_beside_torch_without_writing_beside_the_checkpoint(tmp_path):
    from training.bench_policy import bench_policy

    ckpt = tmp_path / "model.pt"
    shutil.copyfile(SHIPPED, ckpt)
    res = bench_policy(str(ckpt), steps=30, runtime="onnx")
    assert res["onnx"]["median_ms"] > 0 and res["shipped"]["median_ms"] > 0
    assert res["onnx_vs_torch"] == res["shipped"]["median_ms"] / res["onnx"]["median_ms"]
    alone = res["onnx_alone"]  # the same graphs, consecutive steps with nothing in between
    assert alone["kind"] == "vision" and 0 < alone["median_ms"] <= alone["p99_ms"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.pt"]  # the export was a copy's
    with pytest.raises(ValueError, match="runtime must be"):
        bench_policy(str(ckpt), steps=5, runtime="tensorrt")


@needs_onnx
def test_the_shipped_export_is_the_shipped_checkpoints():
    """models/ holds the board's graphs beside the checkpoint: `training.ship` re-exports on
    every ship, so a stale pair here would be refused by every companion on `--runtime auto`."""
    from companion.onnx_runtime import load_onnx_policy

    policy = load_onnx_policy(SHIPPED)
    assert policy.config.kind == "vision" and policy.metadata["runtime"] == "onnx"
