"""[visual] ground_image: a user's picture as the ground — checked, placed where the draw says,
mirrored beyond its edges, lit and affected as the procedural grounds are."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import hover_frame, scenario_with
from PIL import Image

from sitl_sim.config import load_sim
from sitl_sim.errors import ConfigError
from sitl_sim.physics.dynamics import quat_from_euler
from sitl_sim.render.ground import PadGeometry
from sitl_sim.render.ground_image import MIN_GROUND_IMAGE_M, ground_image_map
from sitl_sim.render.render_fast import FastRenderer, camera_intrinsics
from sitl_sim.scenario import load_scenario
from sitl_sim.world import episode_world

CAMERA = load_sim().camera
GROUNDS = ["configs/grounds/field_grass.jpg", "configs/grounds/parking_lot.jpg"]
TINY_PAD = PadGeometry(side_m=0.01, cross_length_m=0.01, cross_width_m=0.001)


def _gradient(tmp_path, name="g.png", size=(64, 96)) -> str:
    rows, cols = size
    img = np.zeros((rows, cols, 3), np.uint8)
    img[..., 0] = np.linspace(0, 255, cols)[None, :]  # red grows to the east (right)
    img[..., 1] = np.linspace(0, 255, rows)[:, None]  # green grows to the south (down)
    Image.fromarray(img).save(tmp_path / name)
    return str(tmp_path / name)


# --------------------------------------------------------------------------- checks


@pytest.mark.parametrize(
    "visual,fragment",
    [
        ({"ground_image": "configs/grounds/none.png"}, "[visual] ground_image = 'configs/grou"),
        ({"ground_image": 5}, "[visual] ground_image = 5; expected a file name"),
        ({"ground_image": GROUNDS, "ground_m_per_px": [0.0, 0.1]}, "[visual] ground_m_per_px"),
        ({"ground_image": GROUNDS, "ground_m_per_px": [-1, 0.1]}, "[visual] ground_m_per_px"),
        ({"ground_image": GROUNDS, "terrain": ["sand"]}, "[visual] terrain = ['sand'] and"),
        ({"ground_image": GROUNDS, "ground_m_per_px": [0.01, 0.1]}, "covers 6.4 m across"),
    ],
)
def test_bad_ground_images_name_file_and_key(visual, fragment):
    with pytest.raises(ConfigError) as err:
        scenario_with(visual=visual)
    assert "test.toml" in str(err.value) and fragment in str(err.value), str(err.value)


def test_an_unreadable_or_too_small_picture_says_so(tmp_path):
    (tmp_path / "junk.jpg").write_bytes(b"\xff\xd8 truncated")
    with pytest.raises(ConfigError, match=r"\[visual\] ground_image = .*junk\.jpg.*readable"):
        scenario_with(visual={"ground_image": str(tmp_path / "junk.jpg")})
    small = _gradient(tmp_path, "small.png", (16, 16))
    with pytest.raises(ConfigError, match=r"16 x 16 px; expected 32 to 4096 px a side"):
        scenario_with(visual={"ground_image": small, "ground_m_per_px": 2.0})
    ok = _gradient(tmp_path, "ok.png", (64, 96))
    with pytest.raises(ConfigError) as err:
        scenario_with(visual={"ground_image": ok, "ground_m_per_px": [0.1, 1.0]})
    # 64 px at 0.1 m/px cover 6.4 m: the message says how much, and what m/px would do
    assert "covers 6.4 m across; expected >= 20 m" in str(err.value)
    assert f"ground_m_per_px >= {MIN_GROUND_IMAGE_M / 64:.3g}" in str(err.value)
    scenario_with(visual={"ground_image": ok, "ground_m_per_px": [0.32, 1.0]})  # 20.5 m: accepted


def test_pictures_are_found_beside_the_scenario_file(tmp_path):
    (tmp_path / "pics").mkdir()
    _gradient(tmp_path / "pics", "ground.png", (64, 64))
    scenario = tmp_path / "field.toml"
    scenario.write_text(
        "[initial_state]\naltitude_m = [10.0, 20.0]\nroll_pitch_deg = [0, 0]\nyaw_deg = [0, 0]\n"
        "north_east_m = [0, 0]\nvel_north_east_m_s = [0, 0]\nvel_down_m_s = [0, 0]\n"
        'rate_rad_s = [0, 0]\n[visual]\nground_image = "pics/ground.png"\nground_m_per_px = 0.5\n'
    )
    sc = load_scenario(scenario)
    assert sc.visual.ground_paths == ((tmp_path / "pics" / "ground.png").resolve(),)
    shipped = load_scenario("configs/scenario_field.toml")
    assert shipped.visual.ground_paths[0].name == "field_grass.jpg"
    assert shipped.pad.designs[0].name == "helipad_1m"


# --------------------------------------------------------------------------- draws and maps


def test_draws_are_deterministic_and_vary_per_episode():
    sc = scenario_with(visual={"ground_image": GROUNDS, "ground_m_per_px": [0.05, 0.1]})
    a, b = episode_world(sc, 7, 3).visual, episode_world(sc, 7, 3).visual
    assert a == b and a.ground_image.endswith(("field_grass.jpg", "parking_lot.jpg"))
    draws = [episode_world(sc, 7, i).visual for i in range(12)]
    assert {d.ground_image for d in draws} == {str(p) for p in sc.visual.ground_paths}
    assert all(0.05 <= d.ground_m_per_px <= 0.1 for d in draws)
    assert len({round(d.ground_rotation_deg, 6) for d in draws}) == 12
    assert len({d.ground_anchor for d in draws}) == 12
    # the pictures are drawn after every other key: the rest of the draw is unchanged
    plain = episode_world(scenario_with(visual={}), 7, 3).visual
    unset = {"ground_image": "", "ground_m_per_px": 0.0, "ground_anchor": (0.0, 0.0)}
    assert replace(a, **unset, ground_rotation_deg=0.0) == plain
    record = episode_world(sc, 7, 3).record()["visual"]
    assert record["ground_image"] == a.ground_image and "ground_image" not in plain.to_dict()


@pytest.mark.parametrize("rotation", [0.0, 90.0, 37.0])
def test_the_picture_lies_where_the_draw_says_and_mirrors_beyond_its_edges(tmp_path, rotation):
    path = _gradient(tmp_path)  # 96 x 64 px
    m = ground_image_map(path, 0.5, (0.25, 0.5), rotation)
    rows, cols = m.rgb.shape[:2]
    assert (rows, cols) == (128, 192) and m.periodic
    # mirrored tiling: the texels either side of each edge are equal, and so is the wrap
    assert np.array_equal(m.rgb[:, 95], m.rgb[:, 96]) and np.array_equal(m.rgb[:, 0], m.rgb[:, -1])
    assert np.array_equal(m.rgb[63], m.rgb[64]) and np.array_equal(m.rgb[0], m.rgb[-1])
    # the anchor (a quarter across, half way down the tile) is under the pad
    n, e, _ = m.texel_to_ne @ (0.25 * cols - 0.5, 0.5 * rows - 0.5, 1.0)
    assert abs(n) < 1e-9 and abs(e) < 1e-9
    # one texel right is 0.5 m along the picture's right, one down 0.5 m against its top
    th = np.radians(rotation)
    right = m.texel_to_ne[:2, 0]
    down = m.texel_to_ne[:2, 1]
    assert np.allclose(right, 0.5 * np.array([-np.sin(th), np.cos(th)]))
    assert np.allclose(down, -0.5 * np.array([np.cos(th), np.sin(th)]))


def test_rendered_picture_is_the_right_way_round_and_at_its_scale(tmp_path):
    """Rotation 0, a level camera facing north: the picture's red grows to the right (east),
    its green downward (south), and a step of one image pixel is depth / f metres of it."""
    path = _gradient(tmp_path, size=(256, 256))
    q = quat_from_euler(0.0, 0.0, 0.0)
    m = ground_image_map(path, 0.05, (0.25, 0.25), 0.0)
    fast = FastRenderer(m, TINY_PAD)
    img_r = fast.render((0.0, 0.0, -10.0), q, CAMERA)
    # mono: luma rises with both red (to the east) and green (to the south)
    row, col = img_r[64], img_r[:, 64]
    assert row[100] > row[30] and col[100] > col[30]
    # red rises one grey step per picture pixel (0.05 m), luma by 77/256 of that; an image
    # pixel is 10 m / f of ground (f = 154.5 px: 1.29 picture pixels)
    f = camera_intrinsics(CAMERA)[0, 0]
    slope = (int(row[110]) - int(row[20])) / 90
    assert slope == pytest.approx(77 / 256 * (10.0 / f) / 0.05, rel=0.1)


# --------------------------------------------------------------------------- light and effects


def _image(visual, alt=20.0, pos=(3.0, 4.0)):
    sc = scenario_with(visual={"ground_image": ["configs/grounds/parking_lot.jpg"], **visual})
    return hover_frame(sc, (*pos, -alt)).astype(float)


def test_sun_haze_and_camera_effects_apply_to_a_ground_picture():
    plain = _image({})
    low_sun = _image({"sun_elevation_deg": 10.0})
    assert low_sun.mean() == pytest.approx(
        plain.mean() * (0.45 + 0.55 * np.sin(np.radians(10))), rel=0.03
    )
    hazy, clear = _image({"haze": 0.6}, alt=100.0), _image({}, alt=100.0)
    assert hazy.std() < 0.5 * clear.std() and hazy.mean() > clear.mean() + 30
    flat = _image({"contrast": 0.5})
    assert flat.std() == pytest.approx(0.5 * plain.std(), rel=0.1)
    barrel = _image({"lens_k1": -0.3})
    assert not np.array_equal(barrel, plain)


def test_the_ground_never_ends(tmp_path):
    """Far from the picture (hundreds of metres, many mirrored copies away) the view is still
    the picture's: no border colour (0) anywhere, its grey levels the picture's."""
    sc = scenario_with(visual={"ground_image": GROUNDS, "ground_m_per_px": 0.05})
    ground = episode_world(sc, 1, 2).visual.ground()
    fast = FastRenderer(ground, TINY_PAD)
    img = fast.render((250.0, -280.0, -60.0), quat_from_euler(0.1, 0.0, 1.0), CAMERA)
    assert np.count_nonzero(img == 0) == 0 and img.std() > 5
    assert abs(img.mean() - ground.mono.mean()) < 0.2 * ground.mono.mean()
