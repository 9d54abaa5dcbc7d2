"""A field day for the companion (issue 30): ``visland soak`` flies one companion process through
consecutive lockstep flights against the SITL and judges its memory, descriptors and latency.
The default suite flies a short day; the 500-flight one is ``slow``."""

from __future__ import annotations

import itertools
import json
import sys

import numpy as np
import pytest
from flights import fly_quietly
from helpers import visland

from tools.soak import LIMITS, SoakConfig, latency_holds, latency_windows, soak
from training.exec.fly import FlyError

SITL = "sitl_sim.mavlink.sitl"


def _after(prelude: str, module: str, name: str) -> tuple[str, ...]:
    """A process's command: ``module.main()`` as ``name``, once ``prelude`` (Python) has run."""
    main = f"from {module} import main\nsys.argv = [{name!r}, *sys.argv[1:]]\nsys.exit(main())\n"
    return (sys.executable, "-c", f"import sys\n{prelude}\n{main}")


def _companion_after(prelude: str) -> tuple[str, ...]:
    """FlyConfig.companion_command: the companion process, once ``prelude`` has run."""
    return _after(prelude, "training.companion_process", "companion")


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


def test_latency_is_judged_on_windows_a_hiccup_passes_and_a_slowing_loop_fails():
    """One flight's p99 is one scheduler hiccup (CI once saw 1.1 -> 2.7 ms between two single
    flights of a 24-flight day); a loop that slows a little every flight fails all the same."""
    calm = [1.1] * 8 + [1.1, 1.2, 1.0, 1.1, 1.1, 1.3, 1.1, 1.2, 1.1, 1.0, 4.0, 1.2, 1.1, 2.7]
    first, last = latency_windows(calm, warmup=8)
    assert latency_holds(first, last), (first, last)
    loaded_end = [*calm[:-5], 2.5, 2.8, 3.0, 2.6, 2.7]  # another job shares the cores at the end
    assert latency_holds(*latency_windows(loaded_end, warmup=8))
    slowing = [1.0 + 0.05 * n for n in range(200)]  # +50 us a flight: a list that grows
    first, last = latency_windows(slowing, warmup=20)
    assert not latency_holds(first, last), (first, last)
    assert first == pytest.approx(np.median(slowing[20:38])) and last == np.median(slowing[-18:])


@pytest.mark.slow
def test_a_field_day_of_500_flights(tmp_path):
    r = soak(SoakConfig(flights=500, out=str(tmp_path / "run"), progress=False))
    assert r.ok, r.to_dict()


def test_card_a_full_card_mid_flight_stops_the_log_not_the_flight(tmp_path):
    """The companion's log hits a 300 kB file-size limit (as a full SD card fails a write)
    mid-flight: it lands all the same, tells the pilot (STATUSTEXT) and its stderr, and the part
    written reads back as a truncated log."""
    from companion.flightlog import read_log

    limited = "import resource; resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))"
    report = fly_quietly(
        tmp_path / "run",
        policy="models/visland_vision.pt",
        episodes=1,
        companion_command=_companion_after(limited),
        companion_args=("--max-age-ms", "3000"),
        sitl_args=("--lockstep-timeout-s", "5"),
    )
    assert report.summary.success_rate == 1.0, report.per_episode
    (log_path,) = (tmp_path / "run" / "companion").glob("*.mcap")
    log = read_log(log_path)
    assert log.truncated and log.topic("/camera/image")  # the part written reads back
    assert log_path.stat().st_size <= 300_000
    assert "flight log stopped" in (tmp_path / "run" / "companion.log").read_text()
    (sitl_log,) = (tmp_path / "run" / "sitl").glob("*.mcap")
    texts = [m["text"] for m in read_log(sitl_log).topic("/mavlink/in/STATUSTEXT")]
    assert any("flight log stopped" in t for t in texts), texts


def test_card_the_sitls_log_filling_the_disk_mid_flight_stops_the_log_not_the_flight(tmp_path):
    """The SITL's episode log hits a 400 kB file-size limit (a full disk) mid-flight: the
    flight lands all the same, the SITL says so in a STATUSTEXT (the companion logs it) and on
    its stderr, and the part written reads back as a truncated log."""
    from companion.flightlog import read_log

    limited = "import resource; resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))"
    run = tmp_path / "run"
    with pytest.raises(FlyError, match=r"0 of 2 episodes finished \(2 SITL logs cut"):
        # the results are in the cut logs: fly cannot report them, and says why
        fly_quietly(run, policy="expert", episodes=2, sitl_command=_after(limited, SITL, "sitl"))
    stderr = (run / "sitl.log").read_text()
    assert stderr.count("flight log stopped: File too large") == 2
    ended = [line for line in stderr.splitlines() if " ended: " in line]
    assert len(ended) == 2 and all("'success': True" in line for line in ended)  # flew on
    logs = sorted((run / "sitl").glob("*.mcap"))
    assert len(logs) == 2
    for path in logs:
        log = read_log(path)
        assert log.truncated and log.topic("/groundtruth/state"), path  # the part written
        assert path.stat().st_size <= 400_000
    flights = json.loads((run / "companion.json").read_text())["flights"]
    assert [f["result"] for f in flights] == ["landed", "landed"], flights
    texts = [
        m["text"]
        for path in sorted((run / "companion").glob("*.mcap"))
        for m in read_log(path).topic("/mavlink/in/STATUSTEXT")
    ]
    assert any(t.startswith("SITL flight log stopped") for t in texts), texts


def test_card_the_wall_clock_stepping_an_hour_mid_flight_changes_nothing_but_a_note(tmp_path):
    """NTP steps the board's clock by +1 h during a flight: no staleness failsafe (control runs
    on the monotonic clock), the log's times go on without a jump, and the step is noted."""
    from companion.flightlog import read_log

    # the step comes once the first flight's log exists (mid-flight), not after a wall-clock
    # delay: on a loaded machine the companion's start alone can outlast any fixed delay
    logs_dir = tmp_path / "run" / "companion"
    stepped = (
        "import pathlib, threading, time\n"
        "real, real_ns = time.time, time.time_ns\n"
        "def later():\n"
        f"    while not list(pathlib.Path({str(logs_dir)!r}).glob('*.mcap')):\n"
        "        time.sleep(0.05)\n"
        "    time.time = lambda: real() + 3600.0\n"
        "    time.time_ns = lambda: real_ns() + 3_600_000_000_000\n"
        "threading.Thread(target=later, daemon=True).start()"
    )
    report = fly_quietly(
        tmp_path / "run", policy="expert", episodes=2, companion_command=_companion_after(stepped)
    )
    assert report.summary.success_rate == 1.0, report.per_episode
    assert report.companion_flights == {"landed": 2}  # no failsafe
    logs = sorted((tmp_path / "run" / "companion").glob("*.mcap"))
    notes = [
        e["text"]
        for log in logs
        for e in read_log(log).topic("/events")
        if e["kind"] == "clock_step"
    ]
    assert len(notes) == 1 and "+3600" in notes[0], notes
    for log in logs:
        times = [m["time_s"] for m in read_log(log).topic("/companion/command")]
        assert times == sorted(times) and max(b - a for a, b in itertools.pairwise(times)) < 5.0
