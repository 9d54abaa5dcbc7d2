"""Guard rails and one vocabulary across ``visland``'s commands (issue 31): refused inputs exit
2 naming why, the text output names what it flew, every option says its default once, old
flag spellings still work and warn, and nothing extra (a pybullet banner, a traceback) reaches
the user's terminal."""

from __future__ import annotations

import argparse
import math
import re
import subprocess
import sys
from io import StringIO
from pathlib import Path

import numpy as np
import pytest
from helpers import visland

from sitl_sim.config import CONFIG_DIR
from sitl_sim.metrics import EpisodeResult, summarize
from sitl_sim.physics.dynamics import ContactEvent
from tools.cli import _parser
from training.evaluate import format_table
from training.reports import EvalReport
from training.seeds import EVAL_SEED

REPO = Path(__file__).resolve().parent.parent


def _parsers(parser: argparse.ArgumentParser, name: str = "visland"):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, child in action.choices.items():
                yield from _parsers(child, f"{name} {sub}")


# --------------------------------------------------------------------------- guard rails


def test_eval_refuses_a_vision_policy_without_the_camera():
    proc = visland("eval", "--policy", "models/visland_vision.pt", "--no-camera")
    assert proc.returncode == 2, proc.stderr
    assert "is a vision policy" in proc.stderr and "fly blind" in proc.stderr
    assert proc.stdout == ""


def test_eval_of_one_episode_names_its_scenario_and_prints_no_pybullet_banner():
    proc = visland("eval", "--episodes", "1", "--no-camera")
    assert proc.returncode == 0, proc.stderr
    assert "pybullet build time" not in proc.stdout + proc.stderr
    assert f"expert: 1 episodes, seed {EVAL_SEED}, scenario configs/scenario.toml" in proc.stdout


def test_eval_refuses_a_scenario_out_of_physical_bounds_naming_file_key_expected_got(tmp_path):
    bad = tmp_path / "hurricane.toml"
    text = (CONFIG_DIR / "scenario.toml").read_text()
    bad.write_text(text + "\n[wind]\nspeed_m_s = [200.0, 300.0]\ndirection_deg = [0, 360]\n")
    proc = visland("eval", "--episodes", "1", "--no-camera", "--scenario", str(bad))
    assert proc.returncode == 2
    (line,) = proc.stderr.strip().splitlines()
    assert str(bad) in line and "[wind] speed_m_s = [200.0, 300.0]" in line
    assert "expected finite [lo, hi] with 0 <= lo <= hi <= 50 (m/s)" in line


def _report(*results: EpisodeResult) -> EvalReport:
    """An eval report of ``results``, read as ``visland eval --json`` would be."""
    head = {"policy": "p", "transport": "inprocess", "seed": 1, "scenario": "s.toml"}
    tail = {"policy_stats": {}, "wall_s": 0.0, "per_episode": []}
    return EvalReport.from_dict({**head, **summarize(list(results)), **tail}, "test")


def test_a_timed_out_flight_never_enters_the_landing_error_mean():
    # touchdown 0.4 m north of the pad centre at 0.3 m/s straight down, tilted 2 deg
    landed = EpisodeResult.from_contact(
        ContactEvent(20.0, np.array([0.4, 0.0, 0.0]), np.array([0.0, 0.0, 0.3]), math.radians(2))
    )
    timeout = EpisodeResult.timeout(90.0, [30.0, 40.0, -10.0], [0.0, 0.0, 0.0])
    report = _report(landed, timeout)
    s = report.summary
    assert s.landed == 1 and s.landing_error_m.mean == pytest.approx(0.4)
    out = StringIO()
    format_table(report, out)
    text = out.getvalue()
    assert "mean    0.400" in text and "(over 1 landed; 1 never touched down)" in text

    report = _report(timeout, timeout)
    assert report.summary.landed == 0 and math.isnan(report.summary.landing_error_m.mean)
    out = StringIO()
    format_table(report, out)
    text = out.getvalue()
    assert "landing error          n/a (none of 2 episodes touched down)" in text, text
    assert "mean    0.000" not in text and "timeouts 2" in text


# --------------------------------------------------------------------------- one vocabulary


def test_every_option_has_help_and_says_its_default_at_most_once():
    for name, parser in _parsers(_parser()):
        formatter = parser._get_formatter()
        for action in parser._actions:
            if not action.option_strings or action.help == argparse.SUPPRESS:
                continue
            text = formatter._expand_help(action) if action.help else ""
            assert text, f"{name} {action.option_strings[0]}: no help"
            assert "(default: None)" not in text, (name, text)
            assert not re.search(r"\(default[^()]*\)\s*\(default", text), (name, text)
            if action.default not in (None, False) and action.nargs != 0:
                assert "default" in text, (name, action.option_strings, text)


def test_commands_that_evaluate_default_to_the_evaluation_seed_and_say_so():
    parser = _parser()
    for argv in (["sitl"], ["fly"], ["demo"]):
        assert parser.parse_args(argv).seed == EVAL_SEED, argv
    proc = visland("sitl", "--help")
    assert f"(default: {EVAL_SEED})" in re.sub(r"\s+", " ", proc.stdout)


def test_param_is_repeatable_on_sitl_and_fly_and_takes_the_comma_form(capsys):
    from sitl_sim.mavlink.config import sitl_config_from_args

    parser = _parser()
    args = parser.parse_args(
        [
            "sitl",
            "--autopilot",
            "ardupilot",
            "--param",
            "GUID_OPTIONS=8",
            "--param",
            "PLND_ENABLED=1,PLND_TYPE=1",
        ]
    )
    assert sitl_config_from_args(args).param == "GUID_OPTIONS=8,PLND_ENABLED=1,PLND_TYPE=1"
    fly = parser.parse_args(["fly", "--param", "GUID_OPTIONS=0", "--sitl-param", "A=1,B=2"])
    assert fly.param == ["GUID_OPTIONS=0", "A=1,B=2"]
    assert "--sitl-param is deprecated; use --param" in capsys.readouterr().err
    assert "--sitl-param" not in parser._subparsers._group_actions[0].choices["fly"].format_help()


def test_version_names_the_package_and_the_commit():
    proc = visland("--version")
    assert proc.returncode == 0
    assert re.fullmatch(r"visland \S+ \(git [0-9a-f]{40}(\+dirty)?\)\n", proc.stdout), proc.stdout


def test_a_closed_pipe_ends_the_command_quietly():
    """``visland ... | head``: the reader leaves before the output is written."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "eval", "--episodes", "1", "--no-camera"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
    )
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(300) == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err
