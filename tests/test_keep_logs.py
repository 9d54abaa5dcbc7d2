"""``visland eval --keep-logs DIR [--keep failed|all]`` (issue 30): the logs of the failed (or
all) flights kept, named by condition, seed and episode, their paths in the JSON and the table;
each holds the camera, ground truth, observation, command and the policy's estimate."""

from __future__ import annotations

import json

from helpers import visland

from companion.flightlog import read_log

VISION = "models/visland_vision.pt"


def test_card_eval_keeps_the_failed_flights_logs_with_the_estimate(tmp_path):
    keep = tmp_path / "kept"
    proc = visland(
        "eval", "--policy", VISION, "--scenario", "configs/sites/rover_fast.toml",
        "--episodes", "3", "--keep-logs", str(keep), "--json",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)["per_episode"]
    failed = [r for r in rows if not r["success"]]
    assert failed, "the shipped model is expected to miss a fast rover (the sites baseline)"
    for r in rows:
        if r["success"]:
            assert r["log"] is None
            continue
        assert r["log"] == str(keep / f"eval_s1000000_ep{r['episode']:04d}.mcap")
        log = read_log(r["log"])
        assert not log.truncated
        for topic in ("/camera/image", "/groundtruth/state", "/observation", "/command"):
            assert log.topic(topic), topic
        estimates = log.topic("/policy/estimate")
        assert len(estimates) == len(log.topic("/command"))
        assert any(e["rel_pos_ned_m"] is not None for e in estimates)
        assert log.topic("/episode/result")[-1]["success"] is False
    assert sorted(p.name for p in keep.iterdir()) == sorted(
        f"eval_s1000000_ep{r['episode']:04d}.mcap" for r in failed
    )  # nothing else left there (no staging folder)


def test_a_suite_keeps_all_logs_named_by_condition_and_lists_them(tmp_path):
    suite = tmp_path / "suite.toml"
    suite.write_text(
        "[suite]\nepisodes = 1\nseed = 1000000\n\n"
        '[conditions.nominal]\nscenario = "configs/scenario.toml"\n\n'
        '[conditions.slope]\nscenario = "configs/sites/slope.toml"\n'
    )
    keep = tmp_path / "kept"
    proc = visland(
        "eval", "--suite", str(suite), "--policy", "expert", "--no-camera",
        "--keep-logs", str(keep), "--keep", "all",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    names = sorted(p.name for p in keep.iterdir())
    assert names == ["nominal_s1000000_ep0000.mcap", "slope_s1000000_ep0000.mcap"]
    assert "flight logs kept (2)" in proc.stdout and str(keep / names[1]) in proc.stdout
    # over MAVLink every flight's logs are kept by fly itself: --keep-logs is refused
    proc = visland("eval", "--transport", "mavlink", "--keep-logs", str(keep))
    assert proc.returncode == 2 and "--keep-logs" in proc.stderr
