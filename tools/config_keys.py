"""``python -m tools.config_keys``: print ``docs/config_keys.md``, every key of every
configuration file (scenario, suite, vehicle, simulation, expert) with its type, unit, default,
range and meaning, generated from the declarations (:mod:`sitl_sim.table`) that read them."""

from __future__ import annotations

import sys

from expert.mpc.config import MpcConfig
from sitl_sim.config import CONFIG_SECTIONS
from sitl_sim.scenario import scenario_tables
from sitl_sim.table import keys_markdown
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
)


def config_keys_markdown() -> str:
    """The page, one table per file kind."""
    parts = (keys_markdown(tables, f"## {title}\n\n{text}\n\n") for title, text, tables in PARTS)
    return INTRO + "\n" + "\n".join(parts)


def main() -> int:
    sys.stdout.write(config_keys_markdown())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
