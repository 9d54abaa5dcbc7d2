"""Pad designs: the shipped pad files, their checks, the [pad] section, and both renderers
drawing a pad at its true size, the right way up, over any ground."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from helpers import hover_frame, scenario_with
from PIL import Image

from sitl_sim.config import load_sim
from sitl_sim.errors import ConfigError
from sitl_sim.physics.dynamics import quat_from_euler
from sitl_sim.render.ground import PadGeometry, PadTexture, nominal_ground
from sitl_sim.render.pads import (
    DEFAULT_PAD,
    PATTERNS,
    builtin_pad_paths,
    default_pad,
    load_pad,
)
from sitl_sim.render.render_fast import FastRenderer, camera_intrinsics
from sitl_sim.render.scene import Scene
from sitl_sim.world import episode_world

CAMERA = load_sim().camera


def _write_pad(tmp_path, text: str, image: np.ndarray | None = None, name="p"):
    if image is not None:
        Image.fromarray(image).save(tmp_path / f"{name}.png")
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- pad files


def test_shipped_pads_load_and_draw_what_they_say():
    paths = builtin_pad_paths()
    assert {"paper", "helipad_1m", "quadrant_2m"} <= set(paths)
    assert DEFAULT_PAD in paths
    for name, path in paths.items():
        pad = load_pad(path)
        assert pad.name == name and pad.path == path and pad.pattern in PATTERNS
    paper, heli, quad = (load_pad(paths[n]) for n in ("paper", "helipad_1m", "quadrant_2m"))
    assert paper.size_m == (4.0, 4.0) and heli.size_m == (1.0, 1.0) and quad.size_m == (2.0, 2.0)
    # the paper's pad is today's PadGeometry, exactly (the nominal world's pad)
    assert paper.scene_pad() == PadGeometry() and default_pad().scene_pad() == PadGeometry()
    assert paper.parts() == [("square", 153.0), ("cross", 75.0)]
    # top views: rows = height / m_per_px, row 0 north, column 0 west
    view = quad.top_view(0.01)
    assert view.shape == (200, 200, 3) and view.dtype == np.uint8
    assert view[0, 0].mean() > 200 and view[0, -1].mean() < 50  # north-west white, north-east black
    assert view[-1, 0].mean() < 50 and view[-1, -1].mean() > 200
    h = heli.luma_view(0.01)
    assert h.shape == (100, 100)
    assert h[50, 50] > 200  # the H's crossbar at the centre
    assert h[50, 34] > 200 and h[50, 66] > 200  # its two posts
    assert h[28, 50] < 60 and h[72, 50] < 60  # dark above and below the bar: an H, not an O
    assert h[2, 2] < 60 and h[50, 7] > 200  # dark corner, the white ring
    assert [n for n, _ in heli.parts()] == ["square", "ring", "H"]


def test_an_image_pad_keeps_its_pixels_size_and_levels(tmp_path):
    img = np.zeros((20, 30, 3), np.uint8)
    img[:, :15] = (250, 250, 250)
    img[:10, 15:] = (0, 0, 255)
    path = _write_pad(tmp_path, 'name = "mine"\nsize_m = [1.5, 1.0]\nimage = "p.png"\n', img)
    pad = load_pad(path)
    assert pad.name == "mine" and pad.size_m == (1.5, 1.0) and pad.pattern is None
    assert np.array_equal(pad.top_view(0.05), img)  # 1.5 m / 0.05 = 30 columns
    assert pad.top_view(0.025).shape == (40, 60, 3)
    levels = [v for _, v in pad.parts()]
    assert len(levels) == 3 and levels[0] < 10 and levels[-1] > 240  # black, blue, white
    scene = pad.scene_pad(2.0)
    assert isinstance(scene, PadTexture) and scene.size_m == (3.0, 2.0)
    # grey images are read as RGB
    grey = tmp_path / "g.png"
    Image.fromarray(np.full((8, 8), 77, np.uint8), "L").save(grey)
    g = load_pad(_write_pad(tmp_path, 'size_m = [1, 1]\nimage = "g.png"\n', name="g"))
    assert g.name == "g" and np.all(g.top_view(0.125) == 77)


@pytest.mark.parametrize(
    "text,fragment",
    [
        ('size_m = [1, 1]\npattern = "helipad"\ncolour = "red"\n', "unknown key(s) ['colour']"),
        ('size_m = [0, 1]\npattern = "helipad"\n', "size_m = [0, 1]; expected [width, height]"),
        ('size_m = [1, -2]\npattern = "helipad"\n', "size_m = [1, -2]"),
        ('size_m = 1\npattern = "helipad"\n', "size_m = 1; expected"),
        ('pattern = "helipad"\n', "size_m = None; expected"),
        ('size_m = [1, 1]\npattern = "target"\n', "pattern = 'target'; expected one of"),
        ("size_m = [1, 1]\n", "expected exactly one of pattern"),
        ('size_m = [1, 1]\npattern = "helipad"\nimage = "x.png"\n', "got both"),
        ('size_m = [1, 1]\nimage = "missing.png"\n', "image = "),
        ("size_m = [1, 1\n", "not a readable TOML pad file"),
    ],
)
def test_bad_pad_files_name_file_and_key(tmp_path, text, fragment):
    path = _write_pad(tmp_path, text, name="bad")
    with pytest.raises(ConfigError) as err:
        load_pad(path)
    assert str(path) in str(err.value) and fragment in str(err.value), str(err.value)


def test_unreadable_pad_image_and_missing_pad_file(tmp_path):
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    path = _write_pad(tmp_path, 'size_m = [1, 1]\nimage = "junk.png"\n', name="junk")
    with pytest.raises(ConfigError, match=r"junk\.toml: image = .*junk\.png.*readable PNG"):
        load_pad(path)
    with pytest.raises(ConfigError, match=r"missing\.png"):
        load_pad(_write_pad(tmp_path, 'size_m = [1, 1]\nimage = "missing.png"\n', name="m"))
    with pytest.raises(ConfigError, match=r"nope\.toml: pad file not found"):
        load_pad(tmp_path / "nope.toml")


# --------------------------------------------------------------------------- [pad] section


def test_pad_section_draws_per_episode_from_its_own_stream(tmp_path):
    sc = scenario_with("t.toml", pad={"design": ["helipad_1m", "configs/pads/quadrant_2m.toml"]})
    names = [episode_world(sc, 5, i).pad.name for i in range(16)]
    assert set(names) == {"helipad_1m", "quadrant_2m"}
    assert names == [episode_world(sc, 5, i).pad.name for i in range(16)]  # same seed, same pads
    w = episode_world(sc, 5, 0)
    assert w.visual.pad_design is w.pad  # a pad without [visual]: the nominal look carries it
    assert w.visual.light == 1.0 and w.visual.ground() is nominal_ground()
    assert w.record()["pad"]["design"] == names[0]
    # the section does not move the initial states, nor the [visual] draw
    vis = {"terrain": ["sand"], "sun_elevation_deg": [20.0, 60.0]}
    with_pad = scenario_with("a", visual=vis, pad={"design": "helipad_1m"})
    without = scenario_with("b", visual=vis)
    a, b = episode_world(with_pad, 2, 3).visual, episode_world(without, 2, 3).visual
    assert replace(a, pad_design=None) == b


def test_a_pad_file_relative_to_the_scenario_file(tmp_path):
    (tmp_path / "pads").mkdir()
    _write_pad(tmp_path / "pads", 'size_m = [0.5, 0.5]\npattern = "quadrant"\n', name="tiny")
    where = str(tmp_path / "scenario.toml")
    (tmp_path / "scenario.toml").write_text("")
    sc = scenario_with(where, pad={"design": "pads/tiny.toml"})
    assert sc.pad.designs[0].size_m == (0.5, 0.5)


@pytest.mark.parametrize(
    "pad,fragment",
    [
        ({"design": "configs/pads/none.toml"}, "[pad] design = 'configs/pads/none.toml'; expected"),
        ({"design": 3}, "[pad] design = 3; expected a file name"),
        ({"design": []}, "[pad] design = []"),
        ({"designs": "helipad_1m"}, "[pad] unknown key(s) ['designs']"),
    ],
)
def test_bad_pad_section_names_file_and_key(pad, fragment):
    with pytest.raises(ConfigError) as err:
        scenario_with("test.toml", pad=pad)
    assert "test.toml" in str(err.value) and fragment in str(err.value), str(err.value)


def test_the_paper_pad_section_is_the_nominal_world_bit_for_bit():
    sc = scenario_with("p.toml", pad={"design": "paper"})
    nominal = scenario_with("n.toml")
    w = episode_world(sc, 1, 0)
    assert w.visual is None and w.pad.name == "paper"
    a, b = _frame(sc, 1, 0, "pybullet"), _frame(nominal, 1, 0, "pybullet")
    assert np.array_equal(a, b)


def test_pad_scale_and_colour_jitter_apply_to_any_design():
    sc = scenario_with(
        "j.toml",
        pad={"design": "helipad_1m"},
        visual={"pad_scale": [1.5, 1.5], "pad_colour_jitter": 0.3},
    )
    pad = episode_world(sc, 0, 0).visual.pad()
    assert isinstance(pad, PadTexture) and pad.size_m == (1.5, 1.5)
    plain = load_pad(builtin_pad_paths()["helipad_1m"]).scene_pad()
    assert pad.rgb.shape == plain.rgb.shape and not np.array_equal(pad.rgb, plain.rgb)
    # the dark square and the white H change independently (two colours, two gains)
    ratio = pad.rgb.astype(float) / np.maximum(plain.rgb.astype(float), 1.0)
    dark, white = plain.mono < 100, plain.mono > 200
    assert not np.allclose(ratio[dark].mean(0), ratio[white].mean(0), atol=0.02)


# --------------------------------------------------------------------------- true size


def _frame(scenario, seed, index, renderer, pos=(0.3, -0.2, -12.0)):
    return hover_frame(scenario, pos, renderer, seed, index, euler_rad=(0.02, -0.01, 0.3))


def _white_pad(w, h):
    rgb = np.full((round(h * 100), round(w * 100), 3), 250, np.uint8)
    rgb[:10, :10] = (0, 0, 0)  # a dark mark in the north-west corner
    return PadTexture(rgb=rgb, size_m=(w, h), name="white")


@pytest.mark.parametrize("renderer", ["pybullet", "fast"])
@pytest.mark.parametrize("alt", [3.0, 8.0, 20.0])
def test_a_pad_is_drawn_at_its_true_size_and_the_right_way_up(renderer, alt):
    """A 1.5 m x 1.0 m white pad under a level camera facing north: its width in pixels is
    f w / (alt - top), its height f h / (alt - top) (within one pixel), the north-west mark
    in the top-left corner."""
    pad = _white_pad(1.5, 1.0)
    f = camera_intrinsics(CAMERA)[0, 0]
    q = quat_from_euler(0.0, 0.0, 0.0)
    ground = nominal_ground()
    if renderer == "pybullet":
        with Scene(pad, ground) as scene:
            img = scene.render((0.0, 0.0, -alt), q, CAMERA)
    else:
        img = FastRenderer(ground, pad).render((0.0, 0.0, -alt), q, CAMERA)
    white = img > 200
    rows, cols = np.nonzero(white)
    depth = alt - pad.top_m
    assert abs((cols.max() - cols.min() + 1) - f * 1.5 / depth) <= 1.0
    assert abs((rows.max() - rows.min() + 1) - f * 1.0 / depth) <= 1.0
    if alt <= 8.0:  # the 10 cm mark is over a pixel wide: north-west is the image's top left
        r0, c0 = rows.min(), cols.min()
        assert img[r0, c0] < 100 and img[rows.max(), cols.max()] > 200


def test_pybullet_and_fast_agree_on_a_pad_in_flight():
    """The [pad] helipad through the simulator: same frames from either renderer (noise-free)."""
    sc = scenario_with("h.toml", pad={"design": "helipad_1m"})
    for pos in ((0.3, -0.2, -3.0), (1.0, 0.5, -10.0)):
        a = _frame(sc, 4, 1, "pybullet", pos).astype(int)
        b = _frame(sc, 4, 1, "fast", pos).astype(int)
        assert np.mean(a != b) < 0.01 and np.mean(np.abs(a - b)) < 0.5
    # the pad is there, at its size: ~ f / 3 px across at 3 m
    img = _frame(sc, 4, 1, "fast", (0.0, 0.0, -3.0))
    bright = np.nonzero(img > 180)
    span = bright[1].max() - bright[1].min() + 1
    f = camera_intrinsics(CAMERA)[0, 0]
    assert math.isclose(span, 0.9 * f / 2.98, abs_tol=3)  # the white ring is 0.9 of the mat
