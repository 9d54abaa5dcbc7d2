"""DAgger through the real processes: the SITL's flight log is a training record that
``relabel`` labels, parallel SITL + companion pairs fly any subset of a seed's episodes, and a
pipeline DAgger round flies its learner through them by default."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from companion.contract.topics import TOPIC_COMPANION_COMMAND, TOPIC_RESULT
from companion.flightlog import read_log
from expert.relabel import relabel
from training.dataset import load_episodes
from training.exec.fly import FlyConfig, FlyError, fly
from training.exec.fly_many import _chunks, fly_many
from training.exec.rollout import completed_episode


def test_sitl_log_is_a_training_record_that_relabel_labels(low_scenario, tmp_path):
    """The expert flies through SITL + companion; the SITL log alone gives every control step's
    observation, ground truth and flown command, and the offline labels of that expert flight
    are (to MAVLink's float32) the commands it flew."""
    report = fly(
        FlyConfig(
            policy="expert", episodes=1, seed=3, scenario=low_scenario, out=str(tmp_path / "f")
        )
    )
    (row,) = report.per_episode
    log_path = Path(row.log)
    (rep,) = relabel([log_path], tmp_path / "labels")
    assert rep.ok and rep.steps > 20, rep
    (ep,), errors = load_episodes([(log_path, Path(rep.labels))], with_images=False)
    assert errors == []
    # contiguous control steps from the take-over to touchdown, flight time from 0
    assert np.all(np.diff(ep.frame_id) == 1) and len(ep) == rep.steps
    assert ep.time_s[0] == pytest.approx(0.0) and np.allclose(np.diff(ep.time_s), 0.1)
    assert ep.pos_ned_m[0, 2] < -4.5 and ep.pos_ned_m[-1, 2] > -0.5  # from 5-6 m to the ground
    # the radar reading logged is the one streamed: range = altitude / cos(tilt) + noise
    assert np.all(np.abs(ep.range_m + ep.pos_ned_m[:, 2]) < 0.3)
    # /command of the SITL log = what the companion sent for the same frame (float32 on the wire)
    (comp_log,) = sorted((tmp_path / "f" / "companion").glob("*f000.mcap"))
    sent = {
        m["frame_id"]: [m["thrust_norm"], *m["rate_frd_rad_s"]]
        for m in read_log(comp_log, topics=[TOPIC_COMPANION_COMMAND]).topic(TOPIC_COMPANION_COMMAND)
        if m["policy"] and m["sent"]
    }
    common = [i for i, f in enumerate(ep.frame_id) if int(f) in sent]
    assert len(common) == len(ep)
    flown_by_companion = np.array([sent[int(ep.frame_id[i])] for i in common])
    assert np.max(np.abs(ep.flown - flown_by_companion)) < 1e-6
    # relabelling the expert's own flight gives back its commands (inputs differ only by
    # float32 ground truth on ODOMETRY), but for the yaw rate: a label holds the heading found
    # at its step, the flight held its first (expert.relabel)
    diff = np.abs(ep.label - ep.flown)
    assert diff[:, :3].max() < 5e-3 and diff[:, 3].max() < 0.1


def test_fly_many_flies_any_subset_of_a_seed_across_instances(low_scenario, tmp_path):
    assert _chunks([5, 0, 1, 2, 7, 8], 2) == [(0, 2), (2, 1), (5, 1), (7, 2)]
    cfg = FlyConfig(policy="expert", seed=9, scenario=low_scenario, out=str(tmp_path / "many"))
    done: list[int] = []
    report = fly_many(cfg, [0, 1, 3], instances=2, chunk=2, on_done=done.append)
    assert sorted(done) == [1, 2] and report.runs == 2 and report.instances == 2
    assert [r.episode for r in report.per_episode] == [0, 1, 3]
    assert report.episodes == 3 and report.summary.success_rate == 1.0
    sitl = tmp_path / "many" / "sitl"
    assert sorted(p.name for p in sitl.glob("*.mcap")) == [
        "sitl_seed9_ep0000.mcap",
        "sitl_seed9_ep0001.mcap",
        "sitl_seed9_ep0003.mcap",
    ]
    assert all(completed_episode(p) for p in sitl.glob("*.mcap"))
    # episode 3 flown alone (its SITL started at --first-episode 3) is episode 3 of the seed
    alone = fly(replace_cfg(cfg, tmp_path / "alone", first_episode=3, episodes=1))
    (a,) = alone.per_episode
    (b,) = [r for r in report.per_episode if r.episode == 3]
    assert a.landing_error_m == pytest.approx(b.landing_error_m, abs=1e-9)
    start = read_log(sitl / "sitl_seed9_ep0003.mcap", topics=["/episode/scenario"])
    assert start.topic("/episode/scenario")[0]["episode"] == 3


def replace_cfg(cfg: FlyConfig, out: Path, **kw) -> FlyConfig:
    from dataclasses import replace

    return replace(cfg, out=str(out), sitl_log_dir=None, **kw)


def test_fly_many_names_the_runs_that_failed(low_scenario, tmp_path):
    from companion.policy_net import CheckpointError

    cfg = FlyConfig(policy="expert", seed=0, scenario=low_scenario, out=str(tmp_path / "bad"))
    # a companion that cannot start (bad flag): every run fails, each is named
    broken = replace_cfg(cfg, tmp_path / "bad", companion_args=("--no-such-flag",))
    with pytest.raises(FlyError, match=r"2 of 2 runs failed") as err:
        fly_many(broken, [0, 1, 2], instances=2, chunk=2)
    assert "episodes 0..1" in str(err.value) and "episodes 2..2" in str(err.value)
    assert "companion exited" in str(err.value)
    # a checkpoint that is not there is refused before any process starts
    missing = replace_cfg(cfg, tmp_path / "none", policy=str(tmp_path / "missing.pt"))
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        fly_many(missing, [0], instances=2)
    assert not (tmp_path / "none").exists()


def test_an_aborted_sitl_episode_is_flown_again(tmp_path):
    """A SITL stopped mid-episode logs the result as aborted: resume must not count it."""
    from companion.contract.records import EpisodeResultRecord
    from companion.flightlog import FlightLogWriter
    from sitl_sim.metrics import EpisodeResult

    path = tmp_path / "sitl_seed0_ep0000.mcap"
    result = EpisodeResult.timeout(1.0, [0.0, 0.0, -5.0], [0.0, 0.0, 0.0]).to_dict()
    for aborted in (True, False):
        record = EpisodeResultRecord(episode=0, aborted=aborted, **result)
        with FlightLogWriter(path, {}) as w:
            w.write(TOPIC_RESULT, record.SCHEMA, 1.0, record.to_dict())
        assert completed_episode(path) is not aborted
    with FlightLogWriter(path, {}) as w:  # a result message that is not a whole result
        w.write(TOPIC_RESULT, record.SCHEMA, 1.0, {"episode": 0, "aborted": False})
    assert not completed_episode(path)


def test_pipeline_dagger_round_flies_the_learner_through_sitl_and_companion(low_scenario, tmp_path):
    """A tiny run: expert flights (in process), BC, one DAgger round whose learner rollouts are
    SITL + companion processes; their SITL logs are relabelled and trained on."""
    from training.pipeline import Profile, run_pipeline
    from training.profiles import PROFILES

    tiny = Profile(
        **{
            **PROFILES["quick"].to_dict(),
            "name": "tiny",
            "collect_episodes": 4,
            "bc_steps": 60,
            "dagger_rounds": 1,
            "dagger_rollouts": 3,
            "dagger_steps": 30,
            "validation_episodes": 2,
            "segment_steps": 10,
            "batch_segments": 8,
        }
    )
    assert tiny.rollouts == "mavlink"  # the default
    run = tmp_path / "run"
    records = run_pipeline(
        run, tiny, low_scenario, stages=("collect", "bc", "dagger"), progress=False
    )
    r0 = json.loads((run / "stages" / "dagger_r0.json").read_text())
    assert r0["rollouts"] == "mavlink" and len(r0["pairs"]) == 3
    for log, labels in r0["pairs"]:
        assert Path(log).name.startswith("sitl_seed100_ep")  # the SITL's own log
        assert read_log(Path(labels), topics=["/label/command"]).topic("/label/command")
    assert sorted((run / "flights" / "dagger_r0" / "mavlink").glob("ep*/companion/*.mcap"))
    assert r0["buffer_episodes"] == 4 + 3  # expert flights + the round's learner flights
    assert Path(records["dagger"]["checkpoint"]).exists()
    # a run is one transport: asking for the other names the key
    from dataclasses import replace

    from training.pipeline import PipelineError

    with pytest.raises(PipelineError, match="differs in rollouts"):
        run_pipeline(run, replace(tiny, rollouts="inprocess"), low_scenario, stages=("bc",))
    with pytest.raises(PipelineError, match="rollouts = 'udp'"):
        replace(tiny, rollouts="udp")
