"""``visland log info`` / ``log plot`` on real flight logs of every kind.

The logs are made by the real code: an in-process episode
(``training.exec.rollout.fly_episode``, the ``collect`` path), a SITL episode over UDP landed by
the SITL's own AUTO.LAND, a ``visland fly`` episode (SITL and companion processes: the
companion's own log), and a minimal companion-style
log (``/observation`` + ``/command`` only) written with the flight-log writer. Every flight
starts 5-6 m above the pad with rendering off, so the file runs in about ten seconds.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pymavlink.dialects.v20 import common as mavlink

from companion.contract.topics import TOPIC_COMMAND, TOPIC_OBSERVATION
from companion.flightlog import FlightLogError, FlightLogWriter, read_log
from sitl_sim.env import LandingEnv
from sitl_sim.mavlink.config import SitlConfig
from sitl_sim.mavlink.sitl import MavlinkSitl
from tools.cli import main
from tools.log_plots import (
    _label_groups,
    default_plot_path,
    plot_flight,
    plot_log,
    time_axis_label,
)
from tools.logtool import log_info
from tools.sitl_client import SitlClient
from training.exec.fly import FlyConfig, fly, free_udp_port
from training.exec.rollout import fly_episode, make_policy


@pytest.fixture(scope="module")
def logs(tmp_path_factory, low_scenario: str) -> dict[str, Path]:
    """One log of each kind (plus a truncated copy of the rollout log)."""
    root = tmp_path_factory.mktemp("logs")
    scenario = Path(low_scenario)

    env = LandingEnv(scenario=str(scenario), render_camera=False)
    try:
        rollout = root / "rollout.mcap"
        fly_episode(env, make_policy("cascade", env), 0, 0, rollout, source="cascade")
    finally:
        env.close()

    mav_port, remote_port, cam_port = free_udp_port(), free_udp_port(), free_udp_port()
    cfg = SitlConfig(
        mavlink_port=mav_port,
        remote_port=remote_port,
        camera_port=cam_port,
        gcs=False,
        scenario=str(scenario),
        log_dir=str(root / "sitl"),
        render=False,
        max_wall_s=30.0,
    )
    sitl = MavlinkSitl(cfg)
    thread = threading.Thread(target=sitl.run, daemon=True, name="sitl")
    thread.start()
    try:
        with SitlClient(("127.0.0.1", mav_port), remote_port, cam_port) as client:
            client.wait_for("HEARTBEAT", 5.0)
            assert client.command_long(mavlink.MAV_CMD_NAV_LAND) == 0
            thread.join(30.0)
    finally:
        sitl.stop()
        thread.join(10.0)
    assert not thread.is_alive() and sitl.results and sitl.results[0].landed

    # The on-board record: telemetry as received and commands, no ground truth, no result.
    source = read_log(rollout)
    companion = root / "companion.mcap"
    with FlightLogWriter(companion, {"config": {"companion": {"policy": "test"}}}) as w:
        observations, commands = source.topic(TOPIC_OBSERVATION), source.topic(TOPIC_COMMAND)
        for obs, cmd in zip(observations, commands, strict=True):
            w.write(TOPIC_OBSERVATION, "visland.Observation", obs["time_s"], obs)
            w.write(TOPIC_COMMAND, "visland.Command", cmd["time_s"], {**cmd, "latency_s": 0.01})

    data = rollout.read_bytes()
    truncated = root / "truncated.mcap"
    truncated.write_bytes(data[: len(data) // 2])

    report = fly(
        FlyConfig(
            policy="cascade", episodes=1, seed=0, scenario=str(scenario), out=str(root / "fly")
        )
    )
    assert report.summary.success_rate == 1.0
    onboard = sorted((root / "fly" / "companion").glob("*.mcap"), key=lambda p: p.stat().st_size)
    return {
        "rollout": rollout,
        "sitl": root / "sitl" / "sitl_seed0_ep0000.mcap",
        "companion": companion,
        "truncated": truncated,
        "onboard": onboard[-1],  # the flight's log (a restart may leave an empty second one)
    }


def test_info_of_a_rollout_log_counts_every_topic_and_gives_the_result(logs):
    info = log_info(logs["rollout"])
    assert info["kind"] == "rollout" and not info["truncated"] and info["error"] is None
    steps = info["topics"]["/command"]["count"]
    assert steps > 50
    for topic in ("/camera/image", "/observation", "/groundtruth/state", "/groundtruth/pose"):
        assert info["topics"][topic]["count"] == steps, topic
    assert info["topics"]["/camera/image"]["schema"] == "foxglove.RawImage"
    assert info["topics"]["/groundtruth/state"]["schema"] == "visland.GroundTruth"
    assert info["messages"] == sum(row["count"] for row in info["topics"].values())
    assert info["metadata"] == {
        "config": ["scenario", "sim", "vehicle"],
        "episode": ["episode_index", "seed", "source"],
    }
    assert info["result"]["landed"] and info["result"]["success"]
    assert info["duration_s"] == pytest.approx(info["result"]["time_s"])
    assert info["plot_missing"] == []
    json.dumps(info)  # JSON-ready as is


def test_info_of_a_sitl_log_names_mavlink_topics_and_schemas(logs):
    info = log_info(logs["sitl"])
    assert info["kind"] == "sitl" and not info["truncated"]
    topics = info["topics"]
    assert topics["/mavlink/in/COMMAND_LONG"] == {"count": 1, "schema": "mavlink.COMMAND_LONG"}
    assert topics["/mavlink/out/HEARTBEAT"]["schema"] == "mavlink.HEARTBEAT"
    # 50 Hz attitude vs 10 Hz frames
    assert topics["/mavlink/out/ATTITUDE"]["count"] > 4 * topics["/groundtruth/state"]["count"]
    assert "/command" not in topics and topics["/autopilot/command"]["count"] > 50
    assert set(info["metadata"]["config"]) == {"params", "sim", "sitl", "vehicle"}
    assert info["result"]["landed"] and not info["result"]["aborted"]
    assert info["plot_sources"]["command"] == "/autopilot/command"


def test_info_of_a_truncated_log_keeps_the_readable_prefix(logs):
    full, cut = log_info(logs["rollout"]), log_info(logs["truncated"])
    assert cut["truncated"] and "cut inside a record" in cut["error"]
    assert 0 < cut["topics"]["/groundtruth/state"]["count"] < full["topics"]["/command"]["count"]
    assert cut["result"] is None and cut["duration_s"] < full["duration_s"]


def _png(path: Path) -> np.ndarray:
    with Image.open(path) as img:
        assert img.format == "PNG"
        return np.asarray(img.convert("L"))


@pytest.mark.parametrize("kind", ["rollout", "sitl", "truncated"])
def test_plot_draws_all_four_panels_from_the_best_sources(logs, kind, tmp_path):
    report = plot_flight(logs[kind], tmp_path / f"{kind}.png")
    pixels = _png(report.out)
    assert pixels.shape == (950, 1300) and pixels.std() > 10  # a drawing, not a blank page
    assert report.missing == [] and report.truncated == (kind == "truncated")
    assert report.sources["position"] == "/groundtruth/state"
    assert report.sources["attitude"] == "/groundtruth/state"
    expected = "/autopilot/command" if kind == "sitl" else "/command"
    assert report.sources["command"] == expected


def test_plot_of_a_companion_log_uses_telemetry_and_says_position_is_missing(logs, tmp_path):
    report = plot_flight(logs["companion"], tmp_path / "companion.png")
    assert report.kind == "companion"
    assert report.sources == {
        "position": None,
        "altitude": "/observation",
        "attitude": "/observation",
        "command": "/command",
    }
    assert report.missing == [
        "position: none of /groundtruth/state, /mavlink/in/ODOMETRY in the log"
    ]
    assert _png(report.out).std() > 10


def test_a_real_companion_log_plots_from_its_own_topics(logs, tmp_path):
    info = log_info(logs["onboard"])
    assert info["kind"] == "companion" and not info["truncated"]
    assert info["result"]["result"] == "landed"  # /companion/summary stands in for the result
    report = plot_flight(logs["onboard"], tmp_path / "onboard.png")
    assert report.missing == []
    assert report.sources == {
        "position": "/mavlink/in/ODOMETRY",  # ground truth, as a privileged pilot received it
        "altitude": "/mavlink/in/ODOMETRY",
        "attitude": "/companion/observation",
        "command": "/companion/command",
    }
    assert _png(report.out).std() > 10


def test_plot_default_path_is_beside_the_log(logs, tmp_path):
    copy = tmp_path / "ep_s0_00000.mcap"
    copy.write_bytes(logs["rollout"].read_bytes())
    assert plot_log(copy) == tmp_path / "ep_s0_00000.png" == default_plot_path(copy)
    assert default_plot_path("a/b.mcap.part") == Path("a/b.png")


def test_cli_log_info_json_and_plot(logs, tmp_path, capsys):
    assert main(["log", "info", str(logs["sitl"]), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "sitl" and info["result"]["success"]
    assert main(["log", "info", str(logs["truncated"])]) == 0
    text = capsys.readouterr().out
    assert "TRUNCATED" in text and "/groundtruth/state" in text and "result: none" in text
    out = tmp_path / "plots" / "c.png"
    assert main(["log", "plot", str(logs["companion"]), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert out.is_file() and "missing position" in text


def test_log_info_into_a_closed_pipe_ends_quietly(logs):
    """``visland log info F | head``: no BrokenPipeError traceback when the reader leaves."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "log", "info", str(logs["sitl"])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(60) == 0 and "Traceback" not in err and "BrokenPipe" not in err, err


def test_log_plot_leaves_out_empty_panels_and_names_its_clock(logs, tmp_path):
    companion = plot_flight(logs["companion"], tmp_path / "companion.png")
    assert companion.drawn == ("altitude", "attitude", "command")  # no position: no panel
    assert companion.clock == time_axis_label("companion") and "wall time" in companion.clock
    sitl = plot_flight(logs["sitl"], tmp_path / "sitl.png")
    assert sitl.drawn == ("position", "altitude", "attitude", "command")
    assert sitl.clock == "sim time (s)"
    # the first second's arming, mode and state changes share one label, not a smear
    events = [(0.0, "armed"), (0.02, "mode OFFBOARD"), (0.05, "state flying"), (30.0, "landed")]
    assert _label_groups(events, 30.0) == [(0.0, "armed (+2)"), (30.0, "landed")]


@pytest.mark.parametrize("content", [b"", b"not an mcap file\n", b"\x89MCAP0\r"])
def test_cli_rejects_a_file_that_is_not_mcap_with_one_line_and_exit_2(tmp_path, capsys, content):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    with pytest.raises(FlightLogError, match="not an MCAP file"):
        log_info(bad)
    for what in ("info", "plot"):
        assert main(["log", what, str(bad)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not an MCAP file" in err[0] and str(bad) in err[0]
    assert not (tmp_path / "bad.png").exists()
