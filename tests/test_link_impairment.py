"""Link impairment (a scenario's ``[link]``): the model on an injected clock, the section's
checks, and real-time flights of the SITL and the companion as separate processes through a
lossy, jittery link — and through a link that dies mid-flight.

The model's tests pass time in (``now_s``), so no threshold depends on the machine. The flight
cards run in real time, where the machine's load matters: they fly from 5-6 m (seconds of
flight) and assert only what a descheduled process cannot break — the vehicle lands softly,
the companion flew it to touchdown, the counters show the impairment acted.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from sitl_sim.errors import ConfigError
from sitl_sim.link_impairment import (
    STREAMS,
    ImpairedStream,
    LinkConfig,
    LinkImpairment,
    link_config_from_table,
)
from sitl_sim.mavlink_endpoint import SitlError
from sitl_sim.scenario import scenario_from_dict
from sitl_sim.sitl_config import SitlConfig

_INITIAL = {
    "roll_pitch_deg": [0.0, 0.0],
    "yaw_deg": [0.0, 0.0],
    "north_east_m": [0.0, 0.0],
    "altitude_m": [5.0, 6.0],
    "vel_north_east_m_s": [0.0, 0.0],
    "vel_down_m_s": [0.0, 0.0],
    "rate_rad_s": [0.0, 0.0],
}


def _stream(seed: int = 0, **cfg) -> ImpairedStream[int]:
    return ImpairedStream(LinkConfig(**cfg), np.random.default_rng(seed), "test")


def _run(stream: ImpairedStream[int], n: int, period_s: float = 0.01) -> list[tuple[float, int]]:
    """Offer datagrams 0..n-1 every ``period_s`` on a fake clock stepped 1 ms at a time; the
    (release time, datagram) of everything delivered, in delivery order."""
    out: list[tuple[float, int]] = []
    t, k, step = 0.0, 0, 0.001
    end = n * period_s + 1.0
    while t < end:
        if k < n and t >= k * period_s - 1e-12:
            stream.offer(k, t)
            k += 1
        out.extend((t, d) for d in stream.due(t))
        t = round(t + step, 9)
    return out


# --------------------------------------------------------------------------- the model


def test_the_same_seed_gives_the_same_fates_and_another_seed_other_ones():
    cfg = dict(loss_prob=0.2, delay_ms=20.0, jitter_ms=30.0, duplicate_prob=0.1, reorder_prob=0.1)
    a, b, c = (
        _run(_stream(7, **cfg), 500),
        _run(_stream(7, **cfg), 500),
        _run(_stream(8, **cfg), 500),
    )
    assert a == b
    assert a != c


def test_loss_rate_is_within_five_binomial_sigmas_and_nothing_else_happens():
    n, p = 20_000, 0.1
    stream = _stream(1, loss_prob=p)
    for k in range(n):
        stream.offer(k, 0.0)
    delivered = stream.due(0.0)
    st = stream.stats
    sigma = math.sqrt(n * p * (1 - p))  # 42.4 datagrams
    assert abs(st.lost - n * p) < 5 * sigma, st
    assert st.delivered == len(delivered) == n - st.lost
    assert delivered == sorted(delivered)  # no delay: in order, at once
    assert (st.delayed, st.duplicated, st.reordered, st.outage) == (0, 0, 0, 0)


def test_a_delayed_datagram_is_held_until_its_release_time_on_the_injected_clock():
    stream = _stream(delay_ms=50.0)
    stream.offer(b"x", 10.0)
    assert stream.due(10.0) == [] and stream.due(10.0499) == []
    assert stream.next_release_s() == pytest.approx(10.05)
    assert stream.due(10.05) == [b"x"]
    assert stream.held == 0 and stream.stats.delayed == 1 and stream.stats.delivered == 1


def test_jitter_delays_within_its_bound_and_keeps_the_stream_in_order():
    delay, jitter = 0.02, 0.05
    stream = _stream(3, delay_ms=delay * 1e3, jitter_ms=jitter * 1e3)
    out = _run(stream, 400, period_s=0.005)  # 5 ms apart: jitter alone would reorder them
    assert [d for _, d in out] == list(range(400))
    lateness = [t - d * 0.005 for t, d in out]
    assert min(lateness) >= delay - 1e-9
    # the queue may hold a datagram behind an earlier, later-drawn one, never longer than that
    assert max(lateness) <= delay + jitter + 0.001 + 1e-9
    assert np.std(lateness) > 0.005  # it does jitter


def test_duplicates_arrive_twice_and_are_counted():
    stream = _stream(4, duplicate_prob=1.0, delay_ms=5.0, jitter_ms=5.0)
    out = [d for _, d in _run(stream, 50)]
    assert sorted(out) == sorted(list(range(50)) * 2)
    assert stream.stats.duplicated == 50 and stream.stats.delivered == 100


def test_reordered_datagrams_overtake_held_ones_and_exactly_those_are_counted():
    stream = _stream(5, delay_ms=30.0, reorder_prob=0.2)
    out = [d for _, d in _run(stream, 300, period_s=0.01)]
    assert sorted(out) == list(range(300))
    # a datagram overtook if an earlier-offered one is delivered after it
    overtakers = sum(1 for i, d in enumerate(out) if any(e < d for e in out[i + 1 :]))
    assert overtakers == stream.stats.reordered > 20


def test_an_outage_drops_everything_and_is_counted_apart_from_loss():
    stream = _stream(loss_prob=0.5)
    for k in range(100):
        stream.offer(k, 0.0, cut=True)
    assert stream.due(1.0) == []
    assert stream.stats.outage == 100 and stream.stats.lost == 0


def test_each_episode_restarts_its_fates_and_streams_do_not_shift_each_other():
    cfg = LinkConfig(loss_prob=0.3)

    def fates(imp: LinkImpairment, stream: str, n: int = 200) -> list[int]:
        s = imp.streams[stream]
        for k in range(n):
            s.offer(k, 0.0)
        return s.due(0.0)

    imp = LinkImpairment(cfg, seed=11, clock=lambda: 0.0)
    imp.start_episode(3)
    first = fates(imp, "mavlink_tx")
    imp.start_episode(3)
    fates(imp, "camera_tx", 1000)  # many camera datagrams first ...
    assert fates(imp, "mavlink_tx") == first  # ... do not change the MAVLink fates
    imp.start_episode(4)
    assert fates(imp, "mavlink_tx") != first
    assert set(imp.stats()) == set(STREAMS)


# --------------------------------------------------------------------------- the section


def test_link_section_parses_with_defaults_and_is_recorded_with_the_scenario():
    sc = scenario_from_dict(
        {"initial_state": _INITIAL, "link": {"loss_prob": 0.1, "jitter_ms": 50}}, "lossy.toml"
    )
    assert sc.link == LinkConfig(loss_prob=0.1, jitter_ms=50.0)
    assert sc.link.delay_ms == 0.0 and sc.link.outage_s is None and sc.link.active
    assert sc.to_dict()["link"]["loss_prob"] == 0.1
    nominal = scenario_from_dict({"initial_state": _INITIAL}, "nominal.toml")
    assert nominal.link is None and "link" not in nominal.to_dict()
    assert not link_config_from_table({}, "empty.toml").active  # an empty [link]: perfect
    cut = link_config_from_table({"outage_s": [2.0, math.inf]}, "cut.toml")
    assert cut.in_outage(2.0) and cut.in_outage(1e6) and not cut.in_outage(1.99)
    assert not cut.in_outage(None)  # not flying: never cut


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ({"loss_prob": 1.5}, r"bad\.toml: \[link\] loss_prob = 1\.5; expected a probability"),
        ({"duplicate_prob": -0.1}, r"bad\.toml: \[link\] duplicate_prob = -0\.1"),
        ({"loss_prob": "10%"}, r"bad\.toml: \[link\] loss_prob = '10%'; expected a probability"),
        ({"delay_ms": -1}, r"bad\.toml: \[link\] delay_ms = -1\.0; expected a finite delay >= 0"),
        ({"jitter_ms": math.nan}, r"bad\.toml: \[link\] jitter_ms = nan"),
        ({"reorder_prob": 0.1}, r"reorder_prob = 0\.1 needs delay_ms or jitter_ms > 0"),
        ({"outage_s": [5.0, 2.0]}, r"outage_s = \[5\.0, 2\.0\]; expected \[start, end\]"),
        ({"outage_s": 3.0}, r"outage_s = 3\.0; expected \[start, end\]"),
        ({"loss": 0.1}, r"bad\.toml: \[link\] unknown key\(s\) \['loss'\]; expected \['loss_prob'"),
    ],
)
def test_bad_link_values_and_unknown_keys_are_config_errors_naming_file_and_key(table, match):
    with pytest.raises(ConfigError, match=match):
        scenario_from_dict({"initial_state": _INITIAL, "link": table}, "bad.toml")


def test_a_misspelt_link_section_is_refused():
    with pytest.raises(ConfigError, match=r"bad\.toml: unknown section\(s\) \['\[links\]'\]"):
        scenario_from_dict({"initial_state": _INITIAL, "links": {}}, "bad.toml")


def test_sitl_link_flags_are_checked_and_an_impaired_link_refuses_lockstep(tmp_path):
    from sitl_sim.mavlink_sitl import MavlinkSitl

    with pytest.raises(SitlError, match=r"link_loss_prob = 2\.0; expected a probability"):
        SitlConfig(link_loss_prob=2.0)
    with pytest.raises(SitlError, match=r"link_jitter_ms = -5\.0; expected a finite number >= 0"):
        SitlConfig(link_jitter_ms=-5.0)
    scenario = tmp_path / "lossy.toml"
    scenario.write_text(
        "[initial_state]\n"
        + "".join(f"{k} = {v}\n" for k, v in _INITIAL.items())
        + "[link]\nloss_prob = 0.1\n"
    )
    with pytest.raises(ConfigError, match=r"lossy\.toml: \[link\].*lockstep.*--no-lockstep"):
        MavlinkSitl(SitlConfig(scenario=str(scenario), lockstep=True, log_dir=None))
    # a flag alone impairs too; and a flag of 0 over the section turns that impairment off
    with pytest.raises(ConfigError, match=r"lockstep"):
        MavlinkSitl(SitlConfig(link_jitter_ms=50.0, log_dir=None))
    t0 = time.monotonic()
    sitl = MavlinkSitl(
        SitlConfig(
            scenario=str(scenario),
            lockstep=True,
            link_loss_prob=0.0,
            log_dir=None,
            render=False,
            gcs=False,
            mavlink_port=0,
            camera_port=9,
        )
    )
    with sitl:
        assert sitl.link_impairment is None
    assert time.monotonic() - t0 < 60
