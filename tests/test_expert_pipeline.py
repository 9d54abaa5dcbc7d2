"""Expert data pipeline: collect (resumable), relabel (exact, truncated, corrupt, wrong vehicle,
NaN), eval JSON, and the landing-metric definitions on hand-made episodes."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from companion.contract.messages import quat_from_euler
from companion.contract.records import GroundTruthRecord
from companion.contract.topics import (
    TOPIC_COMMAND,
    TOPIC_GROUNDTRUTH,
    TOPIC_IMAGE,
    TOPIC_LABEL,
    TOPIC_RESULT,
)
from companion.flightlog import FlightLogWriter, read_log
from expert.mpc import MpcExpert
from expert.mpc.controller import MpcState
from expert.relabel import RelabelError, relabel, relabel_log
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.metrics import EpisodeResult, summarize
from sitl_sim.physics.dynamics import ContactEvent, euler_from_quat
from training.evaluate import CollectConfig, EvalConfig, collect, evaluate


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    report = collect(CollectConfig(out=out, episodes=2, seed=77, progress=False))
    assert report.flown_now == 2 and report.summary.success_rate == 1.0
    return out


def test_collect_writes_complete_logs_and_resumes(run_dir):
    logs = sorted((run_dir / "flights").glob("*.mcap"))
    assert [p.name for p in logs] == ["ep_s77_00000.mcap", "ep_s77_00001.mcap"]
    log = read_log(logs[0])
    assert not log.truncated
    assert log.metadata["config"]["vehicle"]["mass_kg"] == 1.0
    assert log.metadata["episode"] == {"seed": 77, "episode_index": 0, "source": "expert"}
    n = len(log.topic(TOPIC_IMAGE))
    assert n > 100 and len(log.topic(TOPIC_GROUNDTRUTH)) == n == len(log.topic(TOPIC_COMMAND))
    assert log.topic(TOPIC_RESULT)[0]["success"] is True
    again = collect(CollectConfig(out=run_dir, episodes=2, seed=77, progress=False))
    assert again.flown_now == 0 and again.already_complete == 2


def test_relabel_reproduces_the_commands_the_expert_flew(run_dir, tmp_path):
    """Labels are the expert's from each step alone (it holds the heading it finds, where in
    flight it held its first): on its own flight they are its commands up to the small yaw
    corrections it flew back to that first heading."""
    rep = relabel_log(run_dir / "flights" / "ep_s77_00000.mcap", tmp_path)
    assert rep.ok and not rep.truncated
    labels = read_log(rep.labels).topic(TOPIC_LABEL)
    assert len(labels) == rep.steps > 100
    label = np.array([[m["thrust_norm"], *m["rate_frd_rad_s"]] for m in labels])
    flown = np.array([[m["recorded_thrust_norm"], *m["recorded_rate_frd_rad_s"]] for m in labels])
    diff = np.abs(label - flown)
    assert diff[:, 0].max() < 2e-3  # thrust
    assert np.median(diff, axis=0).max() < 1e-3
    assert diff[:, 3].max() < 0.2  # the yaw rate that held the first heading
    assert read_log(run_dir / "flights" / "ep_s77_00000.mcap").topic(TOPIC_RESULT)  # untouched


def test_a_learner_that_turned_is_labelled_to_stop_not_to_turn_back(run_dir, tmp_path):
    """DAgger's expert must be a function of the learner's state: the controller's inputs are
    heading-free, so a label that turned it back to the flight's first heading (as the MPC
    flying with its state would) is one it cannot learn (issue 34: that made round 1 worse)."""
    log = read_log(run_dir / "flights" / "ep_s77_00000.mcap")
    turned = tmp_path / "turned.mcap"
    with FlightLogWriter(turned, log.metadata) as w:
        for topic, msgs in log.messages.items():
            for m in msgs:
                body = {x: v for x, v in m.items() if x != "time_s"}
                if topic == TOPIC_GROUNDTRUTH and m["frame_id"] >= 40:
                    roll, pitch, yaw = euler_from_quat(np.asarray(m["quat_wxyz"]))
                    body["quat_wxyz"] = list(quat_from_euler(roll, pitch, yaw + 0.6))
                w.write(topic, "visland.Any", m["time_s"], body)
    rep = relabel_log(turned, tmp_path / "labels")
    labels = {m["frame_id"]: m for m in read_log(rep.labels).topic(TOPIC_LABEL)}
    assert abs(labels[60]["rate_frd_rad_s"][2]) < 0.05
    # the MPC holding the flight's first heading would turn it back, hard
    truth = {m["frame_id"]: m for m in read_log(turned).topic(TOPIC_GROUNDTRUTH)}
    expert = MpcExpert(load_vehicle(), load_sim())
    first = float(euler_from_quat(np.asarray(truth[0]["quat_wxyz"]))[2])
    gt = GroundTruthRecord.from_dict(truth[60]).groundtruth(truth[60]["time_s"])
    back, _ = expert.act(None, gt, MpcState(yaw_hold_rad=first))  # privileged: no observation
    assert back.rate_frd_rad_s[2] < -0.3


def test_truncated_log_labels_its_prefix_and_corrupt_files_fail_alone(run_dir, tmp_path):
    src = (run_dir / "flights" / "ep_s77_00001.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(src[: len(src) // 2])
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file")
    good = run_dir / "flights" / "ep_s77_00000.mcap"
    reports = relabel([cut, junk, good], tmp_path / "labels")
    by = {r.log.rsplit("/", 1)[-1]: r for r in reports}
    assert by["cut.mcap"].ok and by["cut.mcap"].truncated and 0 < by["cut.mcap"].steps
    assert not by["junk.mcap"].ok and "junk.mcap: not an MCAP file" in by["junk.mcap"].error
    assert by["ep_s77_00000.mcap"].ok


def _copy_with(run_dir, tmp_path, edit_meta=None, edit_truth=None):
    """Rewrite a flight log with its metadata or a ground-truth message altered."""
    log = read_log(run_dir / "flights" / "ep_s77_00000.mcap")
    meta = json.loads(json.dumps(log.metadata))
    if edit_meta:
        edit_meta(meta)
    out = tmp_path / "edited.mcap"
    with FlightLogWriter(out, meta) as w:
        for topic, msgs in log.messages.items():
            if topic == TOPIC_IMAGE:
                continue
            for k, m in enumerate(msgs):
                if topic == TOPIC_GROUNDTRUTH and edit_truth and k == 5:
                    m = edit_truth(dict(m))
                w.write(
                    topic, "visland.Any", m["time_s"], {x: v for x, v in m.items() if x != "time_s"}
                )
    return out


def test_log_from_another_vehicle_is_refused(run_dir, tmp_path):
    def heavier(meta):
        meta["config"]["vehicle"]["mass_kg"] = 2.0

    with pytest.raises(RelabelError, match=r"another vehicle config \(differs in \['mass_kg'\]\)"):
        relabel_log(_copy_with(run_dir, tmp_path, edit_meta=heavier), tmp_path / "l")


def test_nan_in_a_log_names_the_frame(run_dir, tmp_path):
    def nan_pos(m):
        m["pos_ned_m"] = [None, 0.0, -50.0]
        return m

    path = _copy_with(run_dir, tmp_path, edit_truth=nan_pos)
    with pytest.raises(RelabelError, match=r"frame 5: bad record: pos_ned_m"):
        relabel_log(path, tmp_path / "l")


def test_eval_json_has_the_design_keys():
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "eval",
            "--policy",
            "expert",
            "--episodes",
            "2",
            "--seed",
            "123",
            "--no-camera",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    rep = json.loads(proc.stdout)
    for key in ("episodes", "transport", "seed", "success_rate", "per_episode"):
        assert key in rep
    for key in ("landing_error_m", "touchdown_speed_m_s"):
        assert set(rep[key]) == {"min", "max", "mean", "std"}
    assert rep["episodes"] == 2 and rep["transport"] == "inprocess" and rep["seed"] == 123
    assert len(rep["per_episode"]) == 2 and rep["policy_stats"]["failed"] == 0


def test_eval_is_deterministic_across_worker_counts():
    a = evaluate(EvalConfig(episodes=2, seed=9, workers=1, render_camera=False, progress=False))
    b = evaluate(EvalConfig(episodes=2, seed=9, workers=2, render_camera=False, progress=False))
    assert a.per_episode == b.per_episode  # no logs written: log None in both


def _contact(n, e, vel, tilt_deg, t=10.0):
    return ContactEvent(t, np.array([n, e, 0.0]), np.array(vel), math.radians(tilt_deg))


def test_metric_definitions_on_hand_made_episodes():
    good = EpisodeResult.from_contact(_contact(0.3, 0.4, [0.0, 0.3, 0.4], 5.0))
    assert good.landing_error_m == pytest.approx(0.5)
    assert good.touchdown_speed_m_s == pytest.approx(0.5)
    assert good.touchdown_vertical_speed_m_s == pytest.approx(0.4)
    assert good.success
    far = EpisodeResult.from_contact(_contact(1.2, 0.0, [0, 0, 0.2], 0.0))
    hard = EpisodeResult.from_contact(_contact(0.0, 0.0, [0, 0, 1.5], 0.0))
    tilted = EpisodeResult.from_contact(_contact(0.0, 0.0, [0, 0, 0.2], 25.0))
    timeout = EpisodeResult.timeout(90.0, [3.0, 4.0, -10.0], [0, 0, 0])
    assert not any(r.success for r in (far, hard, tilted, timeout))
    assert timeout.landing_error_m == 5.0 and math.isnan(timeout.touchdown_speed_m_s)
    s = summarize([good, far, hard, tilted, timeout])
    assert s["episodes"] == 5 and s["timeouts"] == 1 and s["success_rate"] == pytest.approx(0.2)
    assert s["landed"] == 4  # the timeout never touched down: no landing error in the stats
    assert s["landing_error_m"]["max"] == pytest.approx(1.2) and s["landing_error_m"]["min"] == 0.0
    none = summarize([timeout])
    assert none["landed"] == 0 and math.isnan(none["landing_error_m"]["mean"])
    assert s["touchdown_speed_m_s"]["max"] == pytest.approx(1.5)  # the timeout has no speed
