"""Training worlds: a pipeline run that trains across several scenarios at once.

A worlds file (TOML, e.g. ``configs/train/robust.toml``) names scenario files and the share of
every flight count each gets::

    [worlds.nominal]
    scenario = "configs/scenario.toml"       # relative to the repository root, or absolute
    share = 0.2
    [worlds.mars_mixed]
    scenario = "configs/train/mars_mixed.toml"
    share = 0.3

Every stage that flies (expert collection, DAgger rollouts, validation) splits its episode
count over the worlds by share (largest remainder, so the counts add up) and flies world ``k``
on seed ``seed + k * WORLD_SEED_STRIDE``: world 0 flies exactly the episodes a single-scenario
run would, and no two worlds share a seed. The strides stay far below the evaluation seed
(:data:`training.seeds.EVAL_SEED`). Scenario files (not inline tables) because the MAVLink
rollouts hand the file to ``visland sitl``.

A run without a worlds file has one world: its scenario (:func:`single_world`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sitl_sim.config import load_toml
from sitl_sim.errors import ConfigError
from sitl_sim.scenario import Scenario, load_scenario
from training.seeds import EVAL_SEED
from training.suite import scenario_file

__all__ = [
    "WORLD_SEED_STRIDE",
    "TrainingWorld",
    "WorldMix",
    "load_worlds",
    "single_world",
    "split_count",
]

WORLD_SEED_STRIDE = 10_000
"""Seed offset between consecutive worlds (training seeds are < 1000 per world)."""

_KEYS = ("scenario", "share")


@dataclass(frozen=True)
class TrainingWorld:
    """One world of a run: its name (a folder name under ``flights/<stage>/``, empty for a
    single-scenario run), scenario file, checked scenario, share and seed offset."""

    name: str
    file: str | None
    scenario: Scenario
    share: float
    seed_offset: int


@dataclass(frozen=True)
class WorldMix:
    """The worlds of a run, in file order."""

    path: str | None
    worlds: tuple[TrainingWorld, ...]

    def split(self, count: int) -> list[tuple[TrainingWorld, int]]:
        """``count`` episodes shared out over the worlds (each world with its share)."""
        return list(
            zip(self.worlds, split_count(count, [w.share for w in self.worlds]), strict=True)
        )

    @property
    def planets(self) -> tuple[str, ...]:
        return tuple(sorted({w.scenario.world.name for w in self.worlds}))


def split_count(count: int, shares: list[float]) -> list[int]:
    """``count`` split in proportion to ``shares`` by largest remainder (sums to ``count``)."""
    total = sum(shares)
    exact = [count * s / total for s in shares]
    out = [math.floor(e) for e in exact]
    order = sorted(range(len(shares)), key=lambda k: (-(exact[k] - out[k]), k))
    for k in order[: count - sum(out)]:
        out[k] += 1
    return out


def single_world(scenario: str | None) -> WorldMix:
    """The one world of a run on a single scenario file (None: ``configs/scenario.toml``)."""
    sc = load_scenario(scenario) if scenario else load_scenario()
    return WorldMix(None, (TrainingWorld("", scenario, sc, 1.0, 0),))


def load_worlds(path: str | Path) -> WorldMix:
    """Read and check a worlds file; every scenario is loaded now, so a bad world fails before
    anything flies. Errors name the file, the table and the key."""
    where = str(path)
    data = load_toml(path)
    unknown = sorted(set(data) - {"worlds"})
    if unknown:
        raise ConfigError(f"{where}: unknown top-level key(s) {unknown}; expected [worlds.NAME]")
    tables = data.get("worlds")
    if not isinstance(tables, dict) or not tables:
        raise ConfigError(f"{where}: no [worlds.NAME] tables; expected at least one world")
    if len(tables) * WORLD_SEED_STRIDE >= EVAL_SEED:
        raise ConfigError(f"{where}: {len(tables)} worlds; their seeds would reach the eval seed")
    worlds = []
    for k, (name, table) in enumerate(tables.items()):
        worlds.append(_world(where, k, name, table))
    return WorldMix(where, tuple(worlds))


def _world(where: str, k: int, name: str, table: Any) -> TrainingWorld:
    tag = f"[worlds.{name}]"
    if not name.replace("_", "").isalnum():
        raise ConfigError(f"{where}: {tag}: a world's name is a folder name: letters, digits, _")
    if not isinstance(table, dict):
        raise ConfigError(f'{where}: {tag} must be a table with scenario = "FILE" and share')
    unknown = sorted(set(table) - set(_KEYS))
    if unknown:
        raise ConfigError(f"{where}: {tag} unknown key(s) {unknown}; expected {list(_KEYS)}")
    file = table.get("scenario")
    if not isinstance(file, str):
        raise ConfigError(
            f'{where}: {tag} scenario = {file!r}; expected a scenario file path ("FILE", '
            "relative to the repository root)"
        )
    share = table.get("share")
    if (
        not isinstance(share, int | float)
        or isinstance(share, bool)
        or not math.isfinite(share)
        or share <= 0
    ):
        raise ConfigError(f"{where}: {tag} share = {share!r}; expected a number > 0")
    return TrainingWorld(
        name=name,
        file=file,
        scenario=scenario_file(where, tag, file),
        share=float(share),
        seed_offset=k * WORLD_SEED_STRIDE,
    )
