"""Benchmark suites (``visland eval --suite``): a suite flies each condition exactly as
``evaluate()`` does, bad suite files are ConfigErrors naming file and condition, and the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from flights import LOW_INITIAL_STATE  # low starts: each episode a few simulated seconds
from helpers import visland

from sitl_sim.errors import ConfigError
from sitl_sim.scenario import load_scenario
from training.evaluate import EvalConfig, evaluate
from training.provenance import REPO
from training.reports import EvalReport
from training.suite import load_suite, plot_suite, run_suite

QUIET_EXPERT = EvalConfig("expert", render_camera=False, progress=False)
"""The expert, flown without the camera or a progress bar, as a suite's conditions say."""

LOW_WIND = """
speed_m_s = [2.0, 4.0]
direction_deg = [0.0, 360.0]
turbulence = "light"
gust_m_s = [0.5, 1.0]
"""


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.fixture
def low_file(tmp_path) -> Path:
    return _write(tmp_path / "low.toml", f"[initial_state]\n{LOW_INITIAL_STATE}")


def _suite_file(tmp_path: Path, conditions: str, **suite: int) -> Path:
    """``suite.toml``: a ``[suite]`` table of ``suite``'s keys, then ``conditions``."""
    head = "".join(f"{key} = {value}\n" for key, value in suite.items())
    return _write(tmp_path / "suite.toml", f"[suite]\n{head}\n{conditions}")


def _rows(report: EvalReport) -> str:
    return json.dumps(report.to_dict()["per_episode"], sort_keys=True)  # NaN-safe equality


def test_suite_conditions_fly_exactly_as_evaluate(tmp_path, low_file):
    suite_path = _suite_file(
        tmp_path,
        f"""[conditions.from_file]
scenario = "{low_file}"

[conditions.inline_wind.scenario.initial_state]
{LOW_INITIAL_STATE}
[conditions.inline_wind.scenario.world]
planet = "earth"
[conditions.inline_wind.scenario.wind]
{LOW_WIND}
""",
        episodes=5,
        seed=4242,
    )
    suite = load_suite(suite_path)
    assert [c.name for c in suite.conditions] == ["from_file", "inline_wind"]
    assert suite.conditions[1].scenario.wind is not None
    report = run_suite(suite, QUIET_EXPERT, episodes=2, seed=77)
    assert report.suite == str(suite_path)
    assert (report.episodes, report.seed) == (2, 77)
    assert list(report.conditions) == ["from_file", "inline_wind"]

    wind_file = _write(
        tmp_path / "wind.toml",
        f"[initial_state]\n{LOW_INITIAL_STATE}\n[world]\nplanet = 'earth'\n[wind]\n{LOW_WIND}",
    )
    for name, scenario in (("from_file", low_file), ("inline_wind", wind_file)):
        direct = evaluate(
            EvalConfig(
                policy="expert",
                episodes=2,
                seed=77,
                scenario=str(scenario),
                render_camera=False,
                progress=False,
            )
        )
        got = report.conditions[name]
        assert got.episodes == 2 and got.seed == 77
        assert _rows(got) == _rows(direct), name
        assert got.summary.success_rate == direct.summary.success_rate
    assert report.conditions["inline_wind"].scenario == (f"{suite_path}: [conditions.inline_wind]")

    png = plot_suite(report, tmp_path / "out" / "suite.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_relative_scenario_paths_resolve_against_the_repository(tmp_path, monkeypatch):
    suite_path = _write(
        tmp_path / "s.toml", '[conditions.windy]\nscenario = "configs/scenario_wind.toml"\n'
    )
    monkeypatch.chdir(tmp_path)
    suite = load_suite(suite_path)
    assert (suite.episodes, suite.seed) == (50, 1_000_000)  # defaults without [suite]
    (cond,) = suite.conditions
    assert cond.scenario.source == str(REPO / "configs/scenario_wind.toml")
    assert cond.file == "configs/scenario_wind.toml" and cond.scenario.wind is not None


def test_the_standard_suite_loads():
    suite = load_suite(REPO / "configs/suites/standard.toml")
    names = [c.name for c in suite.conditions]
    assert names == [
        "nominal",
        "wide_initial_states",
        "wind_moderate_gusts",
        "wind_severe",
        "mars",
        "low_sun",
        "unseen_terrain",
        "heavy_vehicle",
        "light_vehicle",
        "sensor_latency_dropouts",
    ]
    by = {c.name: c.scenario for c in suite.conditions}
    assert by["low_sun"].visual.sun_elevation_deg[1] <= 12.0
    # unseen terrain: seeds disjoint from the visual training scenario's
    train = load_scenario(REPO / "configs/scenario_visual.toml").visual.texture_seed
    assert by["unseen_terrain"].visual.texture_seed[0] > train[1]
    assert by["heavy_vehicle"].vehicle.mass_scale[0] >= 1.2
    assert by["light_vehicle"].vehicle.mass_scale[1] <= 0.8
    assert by["sensor_latency_dropouts"].sensors is not None
    assert by["wind_severe"].wind.turbulence == "severe"
    assert by["wide_initial_states"].north_east_m == (-10.0, 10.0)
    assert by["mars"].world.name == "mars"
    assert (suite.episodes, suite.seed) == (50, 1_000_000)


def test_the_compound_suite_holds_conditions_that_come_together():
    suite = load_suite(REPO / "configs/suites/compound.toml")
    by = {c.name: c.scenario for c in suite.conditions}
    assert list(by) == [
        "low_sun_every_ground",
        "mars_wind_faults_low_sun",
        "rover_wind",
        "deck_low_sun",
        "no_pad_in_view",
    ]
    low = by["low_sun_every_ground"].visual
    families = {"regolith", "mars_rocks", "sand", "grass", "asphalt", "gravel"}
    assert set(low.terrain) == families and low.sun_elevation_deg[1] <= 25.0
    train = load_scenario(REPO / "configs/scenario_visual.toml").visual.texture_seed
    assert low.texture_seed[0] > train[1]  # unseen ground
    mars = by["mars_wind_faults_low_sun"]
    assert mars.world.name == "mars"
    assert None not in (mars.wind, mars.sensors, mars.vehicle, mars.visual)
    assert by["rover_wind"].wind is not None
    assert by["deck_low_sun"].visual.sun_elevation_deg[1] <= 25
    # the pad is out of view: at least 150 m off from at most 60 m up (a 45 deg view: 25 m)
    far = by["no_pad_in_view"]
    assert far.north_east_m[0] >= 150.0 and far.altitude_m[1] <= 60.0


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        (
            "[suite]\nepisodes = 2\nrepeats = 3\n",
            ["[suite] unknown key(s) ['repeats']", "expected ['episodes', 'seed']"],
        ),
        ("[sutie]\nepisodes = 2\n", ["top level unknown key(s) ['sutie']"]),
        (
            '[conditions.a]\nscenario = "configs/scenario.toml"\nweight = 2\n',
            ["[conditions.a] unknown key(s) ['weight']", "expected ['scenario', 'episodes']"],
        ),
        (
            '[conditions.a]\nscenario = "configs/scenario.toml"\nepisodes = 0\n',
            ["[conditions.a] episodes = 0", "expected an integer >= 1"],
        ),
        (
            "[conditions.b.scenario.initial_state]\n"
            + LOW_INITIAL_STATE
            + "[conditions.b.scenario.wnd]\nspeed_m_s = [1.0, 2.0]\n",
            ["[conditions.b]: unknown section(s) ['[wnd]']", "expected ['[initial_state]'"],
        ),
        (
            "[conditions.c.scenario.initial_state]\n"
            + LOW_INITIAL_STATE
            + "[conditions.c.scenario.world]\nplanet = 'venus'\n",
            ["[conditions.c]: [world] planet = 'venus'"],
        ),
        (
            '[conditions.d]\nscenario = "configs/no_such_scenario.toml"\n',
            ["[conditions.d] scenario = 'configs/no_such_scenario.toml': file not found"],
        ),
        ("[conditions.e]\n", ["[conditions.e] has no scenario"]),
        ("[suite]\nepisodes = 0\n[conditions.f]\nscenario = 'x'\n", ["[suite] episodes = 0"]),
        ("[suite]\nepisodes = 2\n", ["no [conditions.NAME] tables"]),
    ],
)
def test_bad_suite_files_name_file_and_condition(tmp_path, body, expected):
    path = _write(tmp_path / "bad_suite.toml", body)
    with pytest.raises(ConfigError) as err:
        load_suite(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: "), msg
    for part in expected:
        assert part in msg, msg


def test_missing_suite_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_suite(tmp_path / "nope.toml")


def test_cli_suite_json_and_plot(tmp_path, low_file):
    suite_path = _write(
        tmp_path / "one.toml", f'[suite]\nepisodes = 3\n[conditions.low]\nscenario = "{low_file}"\n'
    )
    png = tmp_path / "suite.png"
    proc = visland(
        "eval", "--suite", str(suite_path), "--episodes", "1", "--no-camera", "--json",
        "--plot", str(png),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["suite"] == str(suite_path)
    assert (report["episodes"], report["seed"], report["policy"]) == (1, 1_000_000, "expert")
    low = report["conditions"]["low"]
    assert low["episodes"] == 1 and len(low["per_episode"]) == 1
    assert low["scenario"] == str(low_file) and low["transport"] == "inprocess"
    assert png.is_file()


@pytest.mark.parametrize(
    ("extra", "flag"),
    [
        (["--scenario", "configs/scenario.toml"], "--scenario"),
        (["--transport", "mavlink"], "--transport mavlink"),
    ],
)
def test_cli_suite_refuses_scenario_and_mavlink(extra, flag):
    proc = visland("eval", "--suite", "configs/suites/standard.toml", *extra)
    assert proc.returncode == 2
    assert "--suite" in proc.stderr and flag in proc.stderr, proc.stderr


def test_cli_plot_without_suite_is_a_usage_error():
    proc = visland("eval", "--plot", "x.png", "--episodes", "1")
    assert proc.returncode == 2 and "--plot and --markdown need --suite" in proc.stderr


def test_a_condition_may_have_its_own_episode_count(tmp_path, low_file):
    suite_path = _suite_file(
        tmp_path,
        f"""[conditions.many]
scenario = "{low_file}"
episodes = 2

[conditions.default]
scenario = "{low_file}"
""",
        episodes=1,
    )
    suite = load_suite(suite_path)
    assert [c.episodes for c in suite.conditions] == [2, None]
    report = run_suite(suite, QUIET_EXPERT)
    assert [r.episodes for r in report.conditions.values()] == [2, 1]
    # --episodes overrides every condition, its own count included
    report = run_suite(suite, QUIET_EXPERT, episodes=1)
    assert [r.episodes for r in report.conditions.values()] == [1, 1]
    assert load_suite(REPO / "configs/suites/standard.toml").conditions[0].episodes == 300
