"""Painted markings on the procedural ground (``[visual] markings``): what a CNN that has only
seen natural ground takes for a pad — drawn, deterministic, wrapping, and absent unless asked."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import scenario_with

from sitl_sim.errors import ConfigError
from sitl_sim.render.terrain import TILE_PX, Sun, terrain_map
from sitl_sim.world import episode_world

SUN = Sun(60.0, 200.0)


def _painted(family: str, seed: int) -> np.ndarray:
    """Where the marked ground is brighter than the same ground without paint (grey levels)."""
    marked = terrain_map(family, seed, SUN, markings=True).mono.astype(float)
    plain = terrain_map(family, seed, SUN).mono.astype(float)
    return marked - plain


@pytest.mark.parametrize("family", ["asphalt", "grass", "regolith"])
def test_markings_paint_bright_thin_lines_on_the_same_ground(family):
    diff = _painted(family, 3)
    painted = diff > 25.0
    # lines a few texels wide over a few per cent of the tile, never darker than the ground
    assert 0.002 < painted.mean() < 0.08, painted.mean()
    assert diff.min() > -1.0
    # the unpainted texels are the plain ground, texel for texel
    assert np.abs(diff[np.abs(diff) < 1.0]).max() == 0.0
    # deterministic per (family, seed), and another seed paints elsewhere
    assert np.array_equal(diff, _painted(family, 3))
    other = _painted(family, 4) > 25.0
    assert (painted & other).sum() < 0.5 * painted.sum()


def test_markings_wrap_around_the_tile_edges():
    # a periodic tile: paint that reaches an edge continues on the opposite edge
    hits = 0
    for seed in range(4):
        painted = _painted("asphalt", seed) > 25.0
        for a, b in ((painted[0], painted[-1]), (painted[:, 0], painted[:, -1])):
            if a.any():
                hits += 1
                assert (a & (np.roll(b, 1) | b | np.roll(b, -1))).sum() >= 0.3 * a.sum()
    assert hits >= 2
    assert terrain_map("asphalt", 0, SUN, markings=True).rgb.shape[:2] == (TILE_PX, TILE_PX)


def test_no_paint_on_the_sea():
    with pytest.raises(ValueError, match="markings on 'water'"):
        terrain_map("water", 1, SUN, markings=True)


def test_the_draw_marks_the_asked_share_and_leaves_other_scenarios_unchanged():
    visual = {"terrain": ["asphalt", "water", "nominal"], "texture_seed": [0, 99]}
    marked = scenario_with(visual={**visual, "markings": 0.6})
    plain = scenario_with(visual=visual)
    draws = [episode_world(marked, 11, i).visual for i in range(60)]
    plains = [episode_world(plain, 11, i).visual for i in range(60)]
    # every key but the markings is the draw without them
    assert [replace(d, markings=False) for d in draws] == plains
    flagged = [d for d in draws if d.markings]
    assert all(d.terrain == "asphalt" for d in flagged)  # not the sea, not the nominal ground
    asphalt = [d for d in draws if d.terrain == "asphalt"]
    assert 0.3 < len(flagged) / len(asphalt) <= 0.9
    assert not any(p.markings for p in plains)
    # the record says so only when painted; the rendered ground is the painted one
    first = flagged[0]
    assert first.to_dict()["markings"] is True and "markings" not in plains[0].to_dict()
    assert first.ground().name.endswith("+markings")


@pytest.mark.parametrize("value", [-0.1, 1.5, "yes"])
def test_a_bad_markings_value_names_the_key(value):
    with pytest.raises(ConfigError, match=r"\[visual\] markings"):
        scenario_with(visual={"markings": value})
