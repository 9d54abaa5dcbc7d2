"""``visland report``: results.md + figures from a small real run; per-episode touchdown."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from companion.policy_net import load_networks, save_checkpoint, untrained_policy
from sitl_sim.config import load_sim
from sitl_sim.env import LandingEnv
from training.exec.rollout import fly_episode, make_policy
from training.paper import PAPER_RUNTIME_S, PAPER_TABLE3
from training.profiles import PROFILES
from training.record import RecordError
from training.report.metrics import ROWS
from training.report.results import ReportConfig, load_metrics, write_report
from training.report.targets import TARGETS
from training.run_folder import Run
from training.stage_records import (
    BcRecord,
    DaggerRecord,
    DaggerRoundRecord,
    FitRecord,
    ValidationScore,
    VisionRecord,
)
from training.stages import eval as eval_stage

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "models" / "visland_vision.pt"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

# ----------------------------------------------------------------------------- stage records


def test_a_fit_stands_inline_in_the_bc_and_dagger_round_records():
    fit = {"steps": 5, "final_loss": None, "seconds": 2.0, "buffer_episodes": 3, "buffer_steps": 40}
    bc = {"stage": "bc", "git_commit": "abc", "checkpoint": "bc.pt", **fit}
    rec = BcRecord.from_dict(bc, "bc.json")
    assert rec.fit == FitRecord(**fit)
    assert list(rec.to_dict().items()) == list(bc.items())  # same keys, same order
    pairs = {"checkpoint": "r0.pt", "rollouts": "r0", "pairs": [["a.mcap", "a.labels"]]}
    round0 = {"stage": "dagger_r0", "git_commit": "abc", **pairs, **fit}
    assert list(DaggerRoundRecord.from_dict(round0).to_dict().items()) == list(round0.items())
    with pytest.raises(RecordError, match=r"bc.json: field buffer_steps is missing"):
        BcRecord.from_dict({k: v for k, v in bc.items() if k != "buffer_steps"}, "bc.json")
    with pytest.raises(RecordError, match=r"unexpected field\(s\) 'fit'"):
        BcRecord.from_dict({**bc, "fit": fit}, "bc.json")


# ----------------------------------------------------------------------------- per-episode field


def test_per_episode_records_where_the_landing_error_was_measured(low_scenario):
    env = LandingEnv(scenario=low_scenario, render_camera=False)
    try:
        out = fly_episode(env, make_policy("cascade", env), seed=3, index=1)
        rest = env.simulator.ground_truth().pos_ned_m  # resting where it touched down
    finally:
        env.close()
    row = out.row()
    assert row.landed and len(row.touchdown_ne_m) == 2
    assert math.hypot(*row.touchdown_ne_m) == pytest.approx(row.landing_error_m, abs=1e-12)
    assert np.allclose(row.touchdown_ne_m, rest[:2], atol=1e-3)
    assert json.loads(row.to_json())["touchdown_ne_m"] == list(row.touchdown_ne_m)

    # a flight that cannot land in 1 s: the position at the timeout, as landing_error_m uses
    short = dataclasses.replace(load_sim(), episode_timeout_s=1.0)
    env = LandingEnv(sim=short, scenario=low_scenario, render_camera=False)
    try:
        out = fly_episode(env, make_policy("expert", env), seed=3, index=1)
        at_timeout = env.simulator.ground_truth().pos_ned_m
    finally:
        env.close()
    row = out.row()
    assert not row.landed and not row.success
    assert row.touchdown_ne_m == pytest.approx(tuple(at_timeout[:2]), abs=1e-12)
    assert math.hypot(*row.touchdown_ne_m) == pytest.approx(row.landing_error_m, abs=1e-12)


# ----------------------------------------------------------------------------- a small real run


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, low_scenario) -> Path:
    """A run folder whose eval stage is the pipeline's own (``training.stages.eval``), 2 episodes a
    row on the low scenario. Checkpoints: BC = an untrained privileged LSTM, DAgger = the
    shipped policy's controller on ground truth (it *is* the paper run's DAgger controller),
    vision = the shipped vision policy. About 15 s."""
    root = tmp_path_factory.mktemp("run") / "tiny"
    profile = dataclasses.replace(PROFILES["quick"], name="tiny", eval_episodes=2, workers=1)
    run = Run(root, profile, low_scenario, progress=False, say=lambda _: None)
    try:
        ck = root / "checkpoints"
        bc = untrained_policy(seed=1, privileged=True)
        save_checkpoint(ck / "bc.pt", bc.config, bc.control, None, {"untrained": True})
        cfg, control, _, meta = load_networks(SHIPPED)
        priv = dataclasses.replace(cfg, kind="privileged")
        save_checkpoint(ck / "dagger.pt", priv, control, None, {"from": str(SHIPPED), **meta})
        shutil.copyfile(SHIPPED, ck / "vision.pt")
        fit = FitRecord(steps=0, final_loss=None, seconds=0.0, buffer_episodes=0, buffer_steps=0)
        picked = {
            "checkpoint": str(ck / "dagger.pt"),
            "selected": str(ck / "dagger.pt"),
            "validation": (ValidationScore(str(ck / "dagger.pt"), 0.0, 0.0, 1.0, 0.0),),
        }
        run.finish(BcRecord("bc", run.commit, str(ck / "bc.pt"), fit))
        run.finish(DaggerRecord("dagger", run.commit, rounds=0, **picked))
        run.finish(
            VisionRecord(
                "vision",
                run.commit,
                fits=(),
                rollouts=None,
                **{**picked, "checkpoint": str(ck / "vision.pt")},
            )
        )
        eval_stage.run(run)
        (root / "scalars.jsonl").write_text(
            "".join(
                json.dumps({"name": f"controller/{s}/loss", "value": 1.0 / (k + 1), "step": k})
                + "\n"
                for s in ("bc", "dagger_r0", "vision_bc")
                for k in range(5)
            )
        )
    finally:
        run.close()
    return root


def _head() -> str:
    return subprocess.run(
        ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=REPO, check=True
    ).stdout.strip()


def _png_ok(path: Path) -> None:
    import matplotlib.image as mpimg

    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, path
    assert len(data) < 150 * 1024, (path, len(data))
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 300, img.shape


def _table_row(md: str, label: str, source: str) -> list[str]:
    prefix = f"| {label} | {source} |"
    line = next(ln for ln in md.splitlines() if ln.startswith(prefix))
    return [c.strip() for c in line[len(prefix) :].strip().strip("|").split("|")]


def test_report_from_a_small_real_run(tiny_run, tmp_path):
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    out = tmp_path / "docs" / "results.md"
    before = _head()
    res = write_report(ReportConfig(run=tiny_run, out=out))
    head = before if before in out.read_text() else _head()  # others may commit meanwhile
    md = out.read_text()

    # Table 3: our numbers are the metrics.json numbers, the paper's are beside them
    for key, label in ROWS.items():
        row = metrics["rows"][key]
        cells = _table_row(md, label, "**ours**")
        for cell, stat in zip(cells[:4], ("min", "max", "mean", "std"), strict=True):
            want = row["landing_error_m"][stat]
            assert float(cell) == pytest.approx(want, rel=2e-2, abs=6e-4), (key, stat)
        assert cells[5] == f"{100 * row['success_rate']:.1f} %"
        speed_mean = float(cells[4].split("/")[0])
        assert speed_mean == pytest.approx(row["touchdown_speed_m_s"]["mean"], abs=6e-4)
        paper = _table_row(md, label, "paper")
        if key in PAPER_TABLE3:
            assert [float(c) for c in paper[:4]] == [
                PAPER_TABLE3[key][s] for s in ("min", "max", "mean", "std")
            ]
        else:
            assert paper[0] == "—"
    assert "| 1.56 | 10.47 | 5.74 | 2.14 |" in md  # paper 5.4, Table 3, BC row

    # runtime: ours from timing, the paper's 125 ms / 13.2 ms and both ratios
    t = metrics["timing"]
    ours = t["mpc"]["median_ms"] / t["policy"]["shipped"]["median_ms"]
    assert f"| **ratio MPC / policy** | {ours:.2f}× | " in md
    assert f"{PAPER_RUNTIME_S['mpc_mean'] / PAPER_RUNTIME_S['policy_mean']:.1f}×" in md
    assert "125 ± 25 ms" in md and "13.2 ± 1.4 ms" in md

    # where we stand: computed from the rows
    met = [tgt.met(load_metrics(tiny_run).rows) for tgt in TARGETS]
    assert res.targets_met == tuple(met)
    assert f"**{sum(met)} of {len(TARGETS)} paper-world targets met.**" in md

    # header: seeds and their disjointness, the run, the commits
    assert f"seed {metrics['eval_seed']}" in md and "disjoint from every seed" in md
    assert head in md and metrics["git_commit"] in md

    # figures: valid PNGs under figures/ beside the markdown, each linked with its provenance
    names = sorted(p.name for p in res.figures)
    assert "landing_scatter.png" in names and "landing_error_hist.png" in names
    assert "training_loss.png" in names
    assert any(n.startswith("trajectory_states_ep") for n in names)
    assert any(n.startswith("trajectory_inputs_ep") for n in names)
    for fig in res.figures:
        assert fig.parent == out.parent / "figures"
        _png_ok(fig)
        assert f"](figures/{fig.name})" in md
    captions = [ln for ln in md.splitlines() if ln.startswith("*Figure ")]
    assert len(captions) == len(res.figures)
    for cap in captions:
        assert f"`visland report --run {tiny_run} --out {out}`" in cap
        assert head[:10] in cap and metrics["git_commit"][:10] in cap

    # the trajectory flights are the eval stage's flights, bit for bit (lockstep determinism)
    assert "reproduces its eval record" in md and "Re-flying does not reproduce" not in md


def test_report_on_a_run_without_touchdown_positions_says_so(tiny_run, tmp_path, capsys):
    from tools.cli import main

    old = tmp_path / "old_run"
    shutil.copytree(tiny_run, old)
    metrics = json.loads((old / "metrics.json").read_text())
    for row in metrics["rows"].values():
        for ep in row["per_episode"]:
            del ep["touchdown_ne_m"]
    (old / "metrics.json").write_text(json.dumps(metrics))
    figs = tmp_path / "figs"
    figs.mkdir()
    (figs / "landing_scatter.png").write_bytes(PNG_MAGIC)  # a stale one from an earlier report
    out = tmp_path / "results.md"
    argv = ["report", "--run", str(old), "--out", str(out), "--figures-dir", str(figs)]
    assert main([*argv, "--no-trajectories"]) == 0
    md = out.read_text()
    assert "Landing scatter unavailable for this run" in md
    assert f"visland train eval --run {old} --profile tiny" in md
    assert not (figs / "landing_scatter.png").exists()
    assert not list(figs.glob("trajectory_*.png"))
    assert "Trajectory figures were skipped" in md
    _png_ok(figs / "landing_error_hist.png")
    assert "scatter unavailable" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("damage", "expect"),
    [
        ("no_run", "no such run folder"),
        ("no_metrics", r"metrics.json: missing; run the pipeline's eval stage"),
        ("corrupt", r"metrics.json: not valid JSON"),
        ("no_vision_row", r"metrics.json: field rows.vision is missing"),
        ("bad_success", r"metrics.json: field rows.bc.success_rate: expected a number or null"),
        ("bad_episode", r"field rows.dagger.per_episode\[1\].touchdown_ne_m: expected \[north"),
    ],
)
def test_bad_runs_are_clear_errors_with_exit_2(tiny_run, tmp_path, capsys, damage, expect):
    import re

    from tools.cli import main

    run = tmp_path / "run"
    if damage != "no_run":
        run.mkdir()
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    if damage == "corrupt":
        (run / "metrics.json").write_text(json.dumps(metrics)[:500])
    elif damage == "no_vision_row":
        del metrics["rows"]["vision"]
    elif damage == "bad_success":
        metrics["rows"]["bc"]["success_rate"] = "all"
    elif damage == "bad_episode":
        metrics["rows"]["dagger"]["per_episode"][1]["touchdown_ne_m"] = [1.0]
    if damage in ("no_vision_row", "bad_success", "bad_episode"):
        (run / "metrics.json").write_text(json.dumps(metrics))
    out = tmp_path / "results.md"
    assert main(["report", "--run", str(run), "--out", str(out), "--no-trajectories"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("visland report: error: ") and re.search(expect, err), err
    assert not out.exists()
