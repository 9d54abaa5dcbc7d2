"""The whole pipeline, every stage, end to end, on a tiny profile: collect → bc → dagger →
perception → vision → eval, then ``visland ship``. Nothing here is built by hand: each stage's
record is the stage's own, DAgger flies the rounds asked for, and the card is written from the
run. Budgets are tiny (the numbers mean nothing); the plumbing is what is tested. A couple of
minutes on two cores."""

from __future__ import annotations

import dataclasses
import json

import torch
from helpers import visland

from companion.files import sha256_file
from companion.policy_net import load_networks
from training.pipeline import run_pipeline
from training.profiles import PROFILES
from training.provenance import SHIPPED_MODEL
from training.ship import ship

TINY = dataclasses.replace(
    PROFILES["quick"],
    name="tiny",
    collect_episodes=4,
    bc_steps=30,
    dagger_rounds=2,
    dagger_rollouts=2,
    dagger_steps=20,
    perception_epochs=1,
    perception_frame_stride=4,
    perception_pose_frames=64,
    vision_bc_steps=20,
    vision_rounds=1,
    vision_rollouts=2,
    vision_steps=20,
    vision_label_gate=True,
    vision_truth_inputs=True,
    eval_episodes=2,
    validation_episodes=2,
    segment_steps=10,
    batch_segments=4,
    workers=2,
    rollouts="inprocess",
)


def _weights(checkpoint) -> dict:
    """A checkpoint's tensors by their path in it (its metadata — run folder, time — left out)."""

    def walk(obj, key=""):
        if isinstance(obj, torch.Tensor):
            yield key, obj
        elif isinstance(obj, dict):
            for k, v in obj.items():
                if k != "metadata":
                    yield from walk(v, f"{key}.{k}")

    return dict(walk(torch.load(checkpoint, weights_only=False)))


def test_every_stage_runs_and_the_card_is_written_from_the_run(tmp_path, low_scenario):
    run = tmp_path / "run"
    records = run_pipeline(run, TINY, low_scenario, progress=False)
    assert list(records) == ["collect", "bc", "dagger", "perception", "vision", "eval"]
    # each stage's record is on disk, as the stage wrote it
    for stage, rec in records.items():
        assert json.loads((run / "stages" / f"{stage}.json").read_text()) == rec, stage
    assert len(records["collect"]["logs"]) == TINY.collect_episodes
    assert records["bc"]["steps"] == TINY.bc_steps
    dagger = records["dagger"]
    assert dagger["rounds"] == TINY.dagger_rounds  # the rounds asked for, all flown
    rounds = sorted(p.name for p in (run / "stages").glob("dagger_r*.json"))
    assert rounds == [f"dagger_r{k}.json" for k in range(TINY.dagger_rounds)]
    # validation scored BC and each round; the pick is one of them
    scored = [v["checkpoint"] for v in dagger["validation"]]
    assert len(scored) == 1 + TINY.dagger_rounds and dagger["selected"] in scored
    assert records["perception"]["epochs"] == TINY.perception_epochs
    assert records["perception"]["train_images"] > 0
    vision = records["vision"]
    assert len(vision["fits"]) == 1 + TINY.vision_rounds  # vision BC, then the rounds
    assert vision["selected"] in [v["checkpoint"] for v in vision["validation"]]
    assert records["eval"]["metrics"] == str(run / "metrics.json")
    metrics = json.loads((run / "metrics.json").read_text())
    assert list(metrics["rows"]) == ["expert", "bc", "dagger", "vision"]
    assert all(r["episodes"] == TINY.eval_episodes for r in metrics["rows"].values())
    assert metrics["rows"]["expert"]["success_rate"] == 1.0  # the expert lands from 5-6 m
    # ship: the run's vision checkpoint, its ONNX export and a card generated from the run
    out = tmp_path / "models"
    model = ship(run, out)
    cfg, _, cnn, _ = load_networks(model)
    assert cfg.kind == "vision" and cnn is not None
    assert sorted(p.name for p in out.glob("*.onnx")) == [
        f"{model.stem}.control.onnx",
        f"{model.stem}.perception.onnx",
    ]
    card = (out / "MODEL_CARD.md").read_text()
    assert f"visland pipeline --profile tiny --out {run}" in card
    assert f"{TINY.dagger_rounds} privileged DAgger" in card and low_scenario in card
    vision_row = metrics["rows"]["vision"]
    row = next(
        line for line in card.splitlines() if line.startswith("| CNN + LSTM (vision) | **ours**")
    )
    assert row.endswith(f"| {vision_row['off_pad']} / {vision_row['aborts']} |"), row

    # a variant (`visland ship --name`) ships beside the default model with its own card, a
    # suite flown with the run's model as a section of it; the default model and card stay
    default = {p.name: p.read_bytes() for p in out.iterdir()}
    suite = tmp_path / "suite.toml"
    suite.write_text(
        f'[suite]\nepisodes = 2\nseed = 1000000\n\n[conditions.low]\nscenario = "{low_scenario}"\n'
    )
    report = tmp_path / "suite.json"
    checkpoint = run / "checkpoints" / "vision.pt"
    proc = visland("eval", "--suite", str(suite), "--policy", str(checkpoint), "--json")
    assert proc.returncode == 0, proc.stderr
    report.write_text(proc.stdout)
    ship_args = ("ship", "--run", str(run), "--out", str(out), "--name", "tiny_sites")
    proc = visland(*ship_args, "--suite-report", str(report))
    assert proc.returncode == 0, proc.stderr
    variant = out / "visland_vision_tiny_sites.pt"
    assert sha256_file(variant) == sha256_file(checkpoint)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name in default} == default
    assert (out / "visland_vision_tiny_sites.control.onnx").is_file()
    vcard = (out / "visland_vision_tiny_sites.md").read_text()
    assert vcard.startswith("# visland vision landing policy `visland_vision_tiny_sites.pt`")
    assert f"--name tiny_sites --suite-report {report}" in vcard
    low = json.loads(report.read_text())["conditions"]["low"]
    assert f"| low | {100 * low['success_rate']:.1f} % (2) |" in vcard
    # a report of another model is refused before anything is written
    other = json.loads(report.read_text())
    other["policy"] = str(SHIPPED_MODEL)  # the repository's model: another sha256
    (tmp_path / "other.json").write_text(json.dumps(other))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    proc = visland(*ship_args[:-1], "other", "--suite-report", str(tmp_path / "other.json"))
    assert proc.returncode == 2 and "is not the model being shipped" in proc.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before

    # one machine, the same profile and seeds: a second run trains the same weights, stage by
    # stage (the card's "Determinism" line says so); only metadata (folder, time) differs
    again = tmp_path / "again"
    run_pipeline(again, TINY, low_scenario, stages=tuple(records)[:-1], progress=False)
    for name in ("bc", "dagger_r1", "perception", "vision_bc", "vision_r0", "vision"):
        first = _weights(run / "checkpoints" / f"{name}.pt")
        second = _weights(again / "checkpoints" / f"{name}.pt")
        assert first.keys() == second.keys() and first, name
        assert all(torch.equal(first[k], second[k]) for k in first), name
