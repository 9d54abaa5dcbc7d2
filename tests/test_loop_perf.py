"""The loop's perf counters (companion.contract.perf) and the SITL's queued flight-log writes
(sitl_sim.mavlink.log_queue): known answers on fake clocks, and a queued log that reads back
exactly as one written on the spot."""

from __future__ import annotations

import pytest

from companion.contract.perf import LoopPerf, parse_perf_line
from companion.flightlog import FlightLogWriter, read_log
from sitl_sim.mavlink.log_queue import LogQueue


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _perf() -> tuple[LoopPerf, _Clock, _Clock]:
    wall, cpu = _Clock(), _Clock()
    return LoopPerf(clock=wall, cpu_clock=cpu), wall, cpu


def test_parts_inner_parts_and_the_window():
    perf, wall, cpu = _perf()
    t = perf.mark(False)  # before the flight: nothing counts
    wall.t = 1.0
    perf.add("physics", t)
    perf.count("frames")
    t = perf.mark(True)  # the flight: 1.0 .. 3.0
    wall.t = 1.5
    t = perf.add("physics", t)
    inner = perf.now()
    wall.t = 1.8
    perf.add_inner("log", inner)  # inside the wait below
    wall.t = 2.5
    perf.add("wait", t)  # 1.0 s less the 0.3 s of log
    perf.count("sim_s", 10.0)
    perf.count("frames")
    wall.t, cpu.t = 3.0, 0.8
    perf.close()
    report = perf.report()
    assert report["window_wall_s"] == pytest.approx(2.0)
    assert report["window_cpu_s"] == pytest.approx(0.8)
    assert report["windows"] == 1
    parts = report["parts_s"]
    assert parts["physics"] == pytest.approx(0.5)
    assert parts["log"] == pytest.approx(0.3)
    assert parts["wait"] == pytest.approx(0.7)
    assert parts["other"] == pytest.approx(0.5)  # 2.5 .. 3.0, claimed by no part
    assert sum(report["shares"].values()) == pytest.approx(1.0)
    assert report["counts"] == {"sim_s": 10.0, "frames": 1.0}
    assert report["realtime_factor"] == pytest.approx(5.0)


def test_an_empty_window_reports_zeros():
    perf, _, _ = _perf()
    perf.close()
    report = perf.report()
    assert report["window_wall_s"] == 0.0
    assert set(report["shares"].values()) == {0.0}
    assert "realtime_factor" not in report


def test_the_perf_line_is_found_in_a_log():
    text = '2026 visland.sitl summary: {}\n2026 visland.sitl perf: {"windows": 2}\ntrailer\n'
    assert parse_perf_line(text) == {"windows": 2}
    assert parse_perf_line("no report here") is None


def _write(writer, n: int) -> None:
    for i in range(n):
        writer.write("/t", "s", 0.1 * i, {"i": i, "x": [1.0, float(i)]})
    writer.write_pose(0.5, [1.0, 2.0, 3.0], [1.0, 0.0, 0.0, 0.0])


def _sans_wall_clock(messages: dict) -> dict:
    """The messages without ``timestamp`` (the file's wall-clock epoch + sim time)."""
    return {
        topic: [{k: v for k, v in m.items() if k != "timestamp"} for m in msgs]
        for topic, msgs in messages.items()
    }


def test_a_queued_log_reads_back_as_one_written_on_the_spot(tmp_path):
    with FlightLogWriter(tmp_path / "direct.mcap", metadata={"m": {"a": 1}}) as direct:
        _write(direct, 20)
    perf, _, _ = _perf()
    queue = LogQueue(perf, max_pending=8)  # 21 writes: two forced drains on the way
    queued = queue.open_writer(tmp_path / "queued.mcap", metadata={"m": {"a": 1}})
    _write(queued, 20)
    assert 0 < queue.pending <= 8
    queue.drain(stop=lambda: True)  # something urgent arrived: nothing written
    assert queue.pending > 0
    queued.close()  # writes what waits, then closes
    assert queue.pending == 0
    a, b = read_log(tmp_path / "direct.mcap"), read_log(tmp_path / "queued.mcap")
    assert not b.truncated
    assert _sans_wall_clock(a.messages) == _sans_wall_clock(b.messages)
    assert a.metadata == b.metadata


def test_max_pending_must_be_positive():
    with pytest.raises(ValueError, match="max_pending = 0"):
        LogQueue(LoopPerf(), max_pending=0)


def test_pin_to_cpus_reads_the_pairs_variables(monkeypatch):
    import os

    from companion.contract.perf import CPUS_ENV, pin_to_cpus

    monkeypatch.delenv(CPUS_ENV["sitl"], raising=False)
    assert pin_to_cpus("sitl") is None  # unset: the kernel places the process
    before = os.sched_getaffinity(0)
    try:
        monkeypatch.setenv(CPUS_ENV["companion"], f" {min(before)} ")
        assert pin_to_cpus("companion") == (min(before),)
        assert os.sched_getaffinity(0) == {min(before)}
        for bad in ("x", "0-", str(os.cpu_count() or 1)):
            monkeypatch.setenv(CPUS_ENV["sitl"], bad)
            with pytest.raises(ValueError, match="VISLAND_SITL_CPUS"):
                pin_to_cpus("sitl")
    finally:
        os.sched_setaffinity(0, before)
