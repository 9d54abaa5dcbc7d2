"""A field day for the companion (issue 30): ``visland soak`` flies one companion process through
consecutive lockstep flights against the SITL and judges its memory, descriptors and latency.
The default suite flies a short day; the 500-flight one is ``slow``."""

from __future__ import annotations

import json

import pytest
from helpers import visland

from tools.soak import LIMITS, SoakConfig, soak


def test_card_visland_soak_a_short_day_holds_memory_descriptors_and_latency(tmp_path):
    proc = visland(
        "soak", "--flights", "24", "--warmup", "8", "--out", str(tmp_path / "run"), "--json",
        timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    r = json.loads(proc.stdout)
    assert r["ok"] and r["flights"] == 24 and r["success_rate"] == 1.0
    assert r["rss_mb"]["growth"] <= LIMITS["rss_growth_mb"]
    assert r["fds"]["end"] <= r["fds"]["warmup"]
    assert len(list((tmp_path / "run" / "companion").glob("*.mcap"))) == 24  # one log a flight
    assert [s["flight"] for s in r["samples"]][:3] == [0, 1, 2]


def test_soak_refuses_fewer_flights_than_it_can_judge():
    with pytest.raises(ValueError, match="--warmup"):
        soak(SoakConfig(flights=15, warmup=10))


@pytest.mark.slow
def test_a_field_day_of_500_flights(tmp_path):
    r = soak(SoakConfig(flights=500, out=str(tmp_path / "run"), progress=False))
    assert r.ok, r.to_dict()
