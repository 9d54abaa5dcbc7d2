"""``python -m tools.config_keys``: print ``docs/config_keys.md``, every key of every
configuration file (scenario, suite, vehicle, simulation, expert, companion) with its type, unit,
default, range and meaning, generated from the declarations (:mod:`companion.table`) that read
them."""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Iterable
from typing import Any

from companion.config import CompanionConfig
from companion.table import REQUIRED, declared_keys, number_text
from expert.mpc.config import MpcConfig
from sitl_sim.config import CONFIG_SECTIONS
from sitl_sim.scenario import scenario_tables
from training.suite import SuiteSection

INTRO = """# Configuration keys

Generated from the declarations that read them by `python -m tools.config_keys >
docs/config_keys.md`; do not edit (`tests/test_table.py` compares it with the code).

The rules are the same for every file. A key left out takes its default; `required` keys have
none. Unknown sections and keys, wrong types and values out of range are `ConfigError`s naming
the file, `[section] key`, what was expected and what was found. A `span` is `[lo, hi]`, drawn
per episode (uniform); a single number `x` means `[x, x]`. A `vector` is a list of exactly that
many numbers.
"""

PARTS = (
    (
        "Scenario files (`configs/scenario*.toml`, `configs/sites/`, a suite's conditions)",
        "A section left out is the nominal world (no wind, the vehicle file as is, the nominal "
        "ground and camera, the paper's pad still on flat ground, no sensor faults, a perfect "
        "link). A `file list` is one file name or a list of them, relative to the scenario file "
        "(else to the repository root).",
        scenario_tables(),
    ),
    (
        "Suite files (`configs/suites/`)",
        "Besides `[suite]`, one `[conditions.NAME]` table per condition: `scenario` (a scenario "
        "file, or an inline table of its sections) and an optional `episodes`.",
        (("suite", SuiteSection),),
    ),
    (
        "`configs/vehicle.toml`",
        "The vehicle's own physics has no default: a missing mass or T_max is refused, never "
        "silently the paper's quad. Each planet flown needs its T_max.",
        tuple((cls.SECTION, cls) for cls in CONFIG_SECTIONS["vehicle.toml"]),
    ),
    (
        "`configs/sim.toml`",
        "Defaults are the shipped file's values (the camera's renderer excepted: the shipped "
        "file picks `fast`).",
        tuple((cls.SECTION, cls) for cls in CONFIG_SECTIONS["sim.toml"]),
    ),
    (
        "`configs/expert.toml`",
        "Defaults are the shipped tuning; a file giving one weight flies it otherwise.",
        (("", MpcConfig),),
    ),
    (
        "The companion's file (`configs/companion.toml`, `companion/assets/companion.toml`)",
        "Every key is also a `visland companion --flag` (underscores become dashes); a flag wins "
        "over the file, the file over the default (the hardware template's). A relative `policy` "
        "(`*.pt`) or `log_dir` is relative to the file's folder. The flight and safety limits are "
        "checked again, against each other, by the safety monitor (`companion.safety`).",
        (("companion", CompanionConfig),),
    ),
)


def _toml(value: Any) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(map(_toml, value)) + "]"
    return (
        number_text(value)
        if isinstance(value, int | float) and not isinstance(value, bool)
        else json.dumps(value)
    )


def _default_text(f: dataclasses.Field) -> str:
    if f.default is REQUIRED:
        return "required"
    if f.default is None:
        return "absent (off)"
    return f"`{_toml(f.default)}`"


def keys_markdown(sections: Iterable[tuple[str, type]], intro: str = "") -> str:
    """A markdown table of every ``(section, class)``'s keys: type, unit, default, range and
    meaning (the generated ``docs/config_keys.md``)."""
    lines = [
        "| section | key | type | unit | default | range | meaning |",
        "|---|---|---|---|---|---|---|",
    ]
    for section, cls in sections:
        for name, (f, key) in declared_keys(cls).items():
            cells = (
                f"`[{key.table or section}]`",
                f"`{name}`",
                key.kind,
                key.unit or "—",
                _default_text(f),
                key.bounds().replace("|", "\\|"),
                key.doc.replace("|", "\\|"),
            )
            lines.append("| " + " | ".join(cells) + " |")
    return intro + "\n".join(lines) + "\n"


def config_keys_markdown() -> str:
    """The page, one table per file kind."""
    parts = (keys_markdown(tables, f"## {title}\n\n{text}\n\n") for title, text, tables in PARTS)
    return INTRO + "\n" + "\n".join(parts)


def main() -> int:
    sys.stdout.write(config_keys_markdown())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
