"""``visland bench sitl`` end to end on a tiny flight: the SITL and the companion as two
processes in lockstep (one low episode, the expert), the in-process floor in the same run, and
a JSON document with every figure the bench promises. No timing thresholds: CI machines are
busy."""

from __future__ import annotations

import json

from companion.contract.perf import PARTS

_SHARES = {"physics", "render", "policy", "encode_decode", "wait", "other"}


def test_bench_sitl_json_has_the_pair_the_floor_and_both_processes_parts(
    tmp_path, low_scenario, capsys
):
    from tools.cli import main

    rc = main(
        [
            "bench",
            "sitl",
            "--json",
            "--checkpoint",
            "expert",
            "--episodes",
            "1",
            "--seed",
            "3",
            "--scenario",
            low_scenario,
            "--repeats",
            "2",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0, out
    res = json.loads(out)
    assert res["config"]["policy"] == "expert" and res["config"]["episodes"] == 1
    assert res["render"] is False  # the expert flies on ground truth: no camera, as fly does
    assert res["frames"] > 0 and res["flight_sim_s"] > 0
    for key in ("realtime_factor", "realtime_factor_cpu", "realtime_factor_end_to_end"):
        assert res[key] > 0, key
    assert res["in_process"]["realtime_factor"] > 0 and res["vs_in_process"] > 0
    for name in ("sitl", "companion"):
        proc = res[name]
        assert set(proc["shares"]) == _SHARES
        assert set(proc["parts_ms_per_frame"]) == set(PARTS) | {"other"}
        assert abs(sum(proc["shares"].values()) - 1.0) < 1e-6
        assert proc["window_wall_s"] > 0 and proc["cpu_ms_per_frame"] > 0
    runs = res["runs"]  # two pairs flew: every run's figures, the best and the median's
    assert len(runs["each"]) == 2 and {runs["best_run"], runs["median_run"]} <= {0, 1}
    rtf = runs["realtime_factor"]
    assert rtf["best"] >= rtf["median"] == res["realtime_factor"] > 0
    assert res["sitl"]["shares"]["physics"] > 0  # the SITL steps the physics ...
    assert res["companion"]["shares"]["policy"] > 0  # ... and the companion flies the expert
