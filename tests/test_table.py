"""The one typed reader of every config file's tables (companion/table.py) and the docs table it
generates."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from typing import ClassVar

import pytest

from companion.table import (
    Section,
    choice,
    integer,
    number,
    probability,
    read_section,
    section_dict,
    section_keys,
    span,
)
from sitl_sim.errors import ConfigError
from sitl_sim.scenario import SECTIONS
from tools.config_keys import config_keys_markdown
from training.provenance import REPO

DOC = REPO / "docs" / "config_keys.md"


@dataclass(frozen=True)
class _Demo(Section):
    SECTION: ClassVar[str] = "demo"

    speed_m_s: tuple[float, float] = span(unit="m/s", lo=0.0, doc="a speed")
    gain: tuple[float, float] = span((1.0, 1.0), unit="1", lo=0.1, hi=5.0, doc="a gain")
    drop_prob: float = probability("a probability")
    delay_ms: float = number(0.0, unit="ms", lo=0.0, noun="a finite delay", doc="a delay")
    count: int = integer(3, unit="1", lo=1, doc="a count")
    level: str = choice("none", ("none", "some"), doc="a level")
    window_s: tuple[float, float] | None = span(
        None, unit="s", doc="a window", ends=("on", "off"), strict=True, finite_hi=False, noun=""
    )


def _read(table: dict) -> _Demo:
    return read_section(_Demo, table, "d.toml")


def test_left_out_keys_take_their_defaults_and_values_are_typed():
    demo = _Demo.from_table(
        {"speed_m_s": [1, 2], "count": 5, "window_s": [2, float("inf")]}, "d.toml"
    )
    assert demo == _Demo(speed_m_s=(1.0, 2.0), count=5, window_s=(2.0, float("inf")))
    assert demo.source == "d.toml" and demo.gain == (1.0, 1.0) and demo.level == "none"
    assert isinstance(demo.speed_m_s[0], float) and isinstance(demo.delay_ms, float)
    assert section_keys(_Demo)[:2] == ("speed_m_s", "gain")
    assert section_dict(demo)["speed_m_s"] == [1.0, 2.0]
    assert "window_s" not in section_dict(_Demo((0.0, 1.0)), drop_none=True)


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ({}, "d.toml: [demo] missing key 'speed_m_s'; expected [lo, hi] (two numbers)"),
        (
            {"speed_m_s": [1, 2], "sped": 1},
            "d.toml: [demo] unknown key(s) ['sped']; expected ['speed_m_s', 'gain', 'drop_prob',",
        ),
        ({"speed_m_s": [1, True]}, "d.toml: [demo] speed_m_s = [1, True]; expected [lo, hi]"),
        (
            {"speed_m_s": [2, 1]},
            "d.toml: [demo] speed_m_s = [2.0, 1.0]; expected finite [lo, hi] with 0 <= lo <= hi "
            "(m/s)",
        ),
        (
            {"speed_m_s": [1, 2], "gain": [0.05, 1]},
            "d.toml: [demo] gain = [0.05, 1.0]; expected finite [lo, hi] with 0.1 <= lo <= hi <= 5",
        ),
        (
            {"speed_m_s": [1, 2], "drop_prob": 1.5},
            "d.toml: [demo] drop_prob = 1.5; expected a probability in [0, 1]",
        ),
        (
            {"speed_m_s": [1, 2], "drop_prob": "5%"},
            "d.toml: [demo] drop_prob = '5%'; expected a probability in [0, 1]",
        ),
        (
            {"speed_m_s": [1, 2], "delay_ms": -1},
            "d.toml: [demo] delay_ms = -1.0; expected a finite delay >= 0 (ms)",
        ),
        (
            {"speed_m_s": [1, 2], "count": 1.0},
            "d.toml: [demo] count = 1.0; expected an integer >= 1",
        ),
        (
            {"speed_m_s": [1, 2], "level": "lots"},
            "d.toml: [demo] level = 'lots'; expected one of ['none', 'some']",
        ),
        (
            {"speed_m_s": [1, 2], "window_s": [3, 3]},
            "d.toml: [demo] window_s = [3.0, 3.0]; expected [on, off] with on < off (s)",
        ),
        ([1, 2], "d.toml: [demo] must be a table, got [1, 2]"),
    ],
)
def test_every_refusal_names_file_section_key_expected_and_got(table, message):
    with pytest.raises(ConfigError) as err:
        _read(table)
    assert str(err.value).startswith(message), str(err.value)


def test_a_section_built_in_code_is_checked_like_one_read_from_a_file():
    with pytest.raises(ConfigError, match=r"<memory>: \[demo\] speed_m_s = \[nan, 1\.0\]"):
        _Demo(speed_m_s=(float("nan"), 1.0))
    with pytest.raises(ConfigError, match=r"\[demo\] level = 'lots'; expected one of"):
        _Demo(speed_m_s=(0.0, 1.0), level="lots")


def test_the_docs_table_is_what_the_declarations_generate():
    """docs/config_keys.md is generated; regenerate it with the command it names."""
    assert DOC.read_text() == config_keys_markdown(), (
        "docs/config_keys.md is stale: python -m tools.config_keys > docs/config_keys.md"
    )
    for section in (*SECTIONS, "suite", "rate_controller", "imu", "camera", "solver"):
        assert f"| `[{section}]` |" in DOC.read_text()


def test_the_docs_table_command_prints_it():
    proc = subprocess.run(
        [sys.executable, "-m", "tools.config_keys"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
        check=True,
    )
    assert proc.stdout == DOC.read_text()
