"""Landing sites (issue 32): the [terrain] section and [pad]'s motion keys are checked and drawn
per episode from their own streams, the nominal world stays bit for bit, and the site model
answers its queries (heights, normals, the pad's pose, the highest surface, ray casts) as the
geometry it was drawn with says."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import flight_frames, rocky_site, scenario_with

from sitl_sim.config import load_sim
from sitl_sim.errors import ConfigError
from sitl_sim.physics.dynamics import quat_from_euler
from sitl_sim.render.render_fast import FastRenderer
from sitl_sim.scenario import InitialStateSampler, load_scenario
from sitl_sim.site.pad_motion import DeckPad, RoverPad
from sitl_sim.world import episode_world

CAMERA = load_sim().camera
SITES = sorted(Path("configs/sites").glob("*.toml"))


# --------------------------------------------------------------------------- draws and config


def test_sites_draw_per_episode_from_their_own_streams():
    visual = {"terrain": ["regolith"], "sun_elevation_deg": [30.0, 60.0]}
    terrain = {"slope_deg": [3.0, 9.0], "relief_m": [0.2, 0.6], "rocks_per_100m2": [1.0, 3.0]}
    pad = {"motion": "rover", "height_m": 1.5, "speed_m_s": [1.0, 2.0], "turn_rate_deg_s": [-5, 5]}
    sc = scenario_with(visual=visual, terrain=terrain, pad=pad)
    a, b = episode_world(sc, 4, 2), episode_world(sc, 4, 2)
    assert a.site.record() == b.site.record()  # same (seed, episode): the same site
    for t in (0.0, 3.3, 17.0):
        pa, pb = a.site.pad_pose(t), b.site.pad_pose(t)
        assert np.array_equal(pa.position_ned, pb.position_ned)
        assert np.array_equal(pa.R_pad_to_ned, pb.R_pad_to_ned)
    assert a.site.ground_height(12.3, -7.9) == b.site.ground_height(12.3, -7.9)
    others = [episode_world(sc, 4, i).site.record() for i in range(5)]
    assert len({json.dumps(r, sort_keys=True) for r in others}) == 5
    assert json.loads(json.dumps(a.record()))["site"] == a.site.record()  # logged, as JSON
    # the sections move no other draw: not the look, not the initial states
    plain = scenario_with(visual=visual)
    assert episode_world(plain, 4, 2).visual == a.visual
    assert InitialStateSampler(sc, 4).sample(2) == InitialStateSampler(plain, 4).sample(2)
    # and neither moves the other: the terrain is the same under a still pad
    still = scenario_with(visual=visual, terrain=terrain)
    assert episode_world(still, 4, 2).site.terrain.record() == a.site.terrain.record()
    moving = scenario_with(visual=visual, pad=pad)
    assert episode_world(moving, 4, 2).site.motion.record() == a.site.motion.record()


def test_the_nominal_site_is_the_nominal_world_bit_for_bit():
    """A still pad at height 0 and no [terrain]: no site, today's world, records and images."""
    explicit = scenario_with(pad={"motion": "static", "height_m": 0.0})
    nominal = scenario_with()
    w = episode_world(explicit, 1, 0)
    assert w.site is None and w.visual is None
    assert w.record() == episode_world(nominal, 1, 0).record() == {}
    for renderer in ("fast", "pybullet"):
        a, b = flight_frames(explicit, renderer), flight_frames(nominal, renderer)
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)), renderer


@pytest.mark.parametrize(
    "sections,fragment",
    [
        ({"terrain": {"slope": [1, 2]}}, "[terrain] unknown key(s) ['slope']"),
        ({"terrain": {"slope_deg": [10.0, 5.0]}}, "[terrain] slope_deg = [10.0, 5.0]; expected"),
        ({"terrain": {"slope_deg": [0.0, 45.0]}}, "[terrain] slope_deg"),
        ({"terrain": {"rock_height_m": [0.0, 0.5]}}, "[terrain] rock_height_m = [0.0, 0.5]"),
        ({"terrain": {"craters_per_km2": "many"}}, "[terrain] craters_per_km2 = 'many'"),
        ({"pad": {"motion": "boat"}}, "[pad] motion = 'boat'; expected one of"),
        ({"pad": {"height_m": [-1.0, 1.0]}}, "[pad] height_m = [-1.0, 1.0]"),
        ({"pad": {"speed_m_s": 2.0}}, "[pad] speed_m_s = [2.0, 2.0] with motion = 'static'"),
        ({"pad": {"motion": "rover", "heave_m": 0.3}}, "[pad] heave_m = [0.3, 0.3] with motion"),
        ({"pad": {"motion": "deck", "turn_rate_deg_s": 3}}, "[pad] turn_rate_deg_s"),
        ({"pad": {"motion": "deck", "roll_deg": [5, 50]}}, "[pad] roll_deg = [5.0, 50.0]"),
        (
            {"pad": {"motion": "deck"}, "terrain": {"slope_deg": 5.0}},
            "[terrain] with [pad] motion = 'deck'",
        ),
    ],
)
def test_bad_site_keys_name_file_and_key(sections, fragment):
    with pytest.raises(ConfigError) as err:
        scenario_with("bad.toml", **sections)
    assert "bad.toml" in str(err.value) and fragment in str(err.value), str(err.value)


def test_keys_left_out_take_their_nominal_values():
    sc = scenario_with(terrain={"relief_m": [0.5, 0.5]})
    assert sc.terrain.slope_deg == (0.0, 0.0) and sc.terrain.rocks_per_100m2 == (0.0, 0.0)
    deck = scenario_with(pad={"motion": "deck", "heave_m": 0.2})
    assert deck.pad.height_m == (0.0, 0.0) and deck.pad.heave_period_s == (6.0, 10.0)
    flat = scenario_with(terrain={})  # an empty [terrain]: flat, bare ground
    site = episode_world(flat, 0, 0).site
    assert site.terrain.heights is None and len(site.terrain.rocks) == 0
    assert site.ground_height(17.0, -4.0) == 0.0


@pytest.mark.parametrize("path", SITES, ids=[p.stem for p in SITES])
def test_example_site_scenarios_draw_what_they_say(path):
    sc = load_scenario(path)
    w = episode_world(sc, 0, 3)
    kind = {"rover": "rover", "deck": "deck"}.get(path.stem.split("_")[0], "static")
    assert w.site is not None and w.site.motion.kind == kind
    assert json.loads(json.dumps(w.record()))["site"]["pad"]["motion"] == kind
    if kind == "deck":
        assert w.visual.terrain == "water" and w.site.water


# --------------------------------------------------------------------------- site queries


def test_ground_height_and_normal_on_a_known_slope():
    site = episode_world(scenario_with(terrain={"slope_deg": 10.0}), 2, 0).site
    az = math.radians(site.terrain.slope_azimuth_deg)
    grade = math.tan(math.radians(10.0))
    for n, e in ((3.0, -4.0), (-20.0, 7.5), (140.0, 55.0), (0.0, 0.0)):
        expected = grade * (n * math.cos(az) + e * math.sin(az))
        assert site.ground_height(n, e) == pytest.approx(expected, abs=1e-9)
    normal = np.array(site.ground_normal(5.0, -3.0))
    assert np.linalg.norm(normal) == pytest.approx(1.0)
    assert -normal[2] == pytest.approx(math.cos(math.radians(10.0)), abs=1e-6)  # 10 deg off up
    downhill = -np.array([math.cos(az), math.sin(az)])
    assert normal[:2] @ downhill == pytest.approx(math.sin(math.radians(10.0)), abs=1e-6)
    # the pad lies on it: its down axis is the ground's, its centre at the origin
    pose = site.pad_pose(0.0)
    assert np.allclose(pose.R_pad_to_ned[:, 2], -normal, atol=1e-9)
    assert np.allclose(pose.position_ned, 0.0) and not pose.velocity_ned.any()


def test_a_ray_cast_meets_a_rock_where_its_surface_is():
    _, site, k, (n, e) = rocky_site()
    top = site.ground_height(n, e)
    assert (
        top == pytest.approx(site.terrain.rocks.top(k, n, e)) and top > 0.25
    )  # on flat ground: the rock
    assert site.range_along((n, e, -20.0), (0.0, 0.0, 1.0), 0.0, 100.0) == pytest.approx(20 - top)
    # slanted rays toward the rock meet a surface: the site's height where they stop
    for direction in ((0.3, 0.2, 1.0), (-0.5, 0.1, 1.0), (0.05, -0.6, 1.0)):
        d = np.array(direction) / np.linalg.norm(direction)
        origin = np.array([n, e, -top]) - 8.0 * d
        r = site.range_along(origin, d, 0.0, 100.0)
        assert r <= 8.0 + 1e-9
        hit = origin + r * d
        assert site.ground_height(hit[0], hit[1]) == pytest.approx(-hit[2], abs=1e-6)
    # no rock on the pad, none near it: the ground there is the plane
    grid = np.linspace(-3.0, 3.0, 25)
    assert max(site.ground_height(a, b) for a in grid for b in grid) == 0.0
    assert site.range_along((0.0, 0.0, -30.0), (0, 0, 1), 0.0, 100.0) == pytest.approx(30.0)
    assert site.range_along((0.0, 0.0, -30.0), (0, 0, 1), 0.0, 10.0) == math.inf  # too far
    assert site.range_along((0.0, 0.0, -30.0), (0.1, 0, -1), 0.0, 100.0) == math.inf  # upward


def test_a_ray_cast_meets_the_relief_where_it_is():
    sc = scenario_with(terrain={"slope_deg": 6.0, "relief_m": 1.0, "craters_per_km2": 2000.0})
    site = episode_world(sc, 7, 0).site
    assert site.terrain.heights is not None and site.terrain.craters
    rng = np.random.default_rng(0)
    for _ in range(20):
        origin = np.array([*rng.uniform(-50.0, 50.0, 2), -40.0])
        d = np.array([*rng.uniform(-0.5, 0.5, 2), 1.0])
        d /= np.linalg.norm(d)
        r = site.range_along(origin, d, 0.0, 200.0)
        hit = origin + r * d
        assert site.ground_height(hit[0], hit[1]) == pytest.approx(-hit[2], abs=1e-5)
        # nothing in the way before it: the ray is above the ground all along
        for s in np.linspace(0.0, r, 40)[:-1]:
            p = origin + s * d
            assert -p[2] >= site.ground_height(p[0], p[1]) - 1e-6


def test_a_rover_with_no_turn_drives_straight_at_its_speed():
    pad = {"motion": "rover", "height_m": 1.4, "speed_m_s": 2.0, "heading_deg": 30.0}
    site = episode_world(scenario_with(pad=pad), 3, 0).site
    assert isinstance(site.motion, RoverPad)
    heading = np.array([math.cos(math.radians(30)), math.sin(math.radians(30))])
    for t in (0.0, 1.3, 7.5, 42.0):
        pose = site.pad_pose(t)
        assert np.allclose(pose.position_ned[:2], 2.0 * t * heading, atol=1e-9)
        assert pose.position_ned[2] == pytest.approx(-1.4)
        assert np.allclose(pose.velocity_ned, [*(2.0 * heading), 0.0], atol=1e-6)
        assert np.allclose(pose.omega_ned, 0.0, atol=1e-9)
        assert np.allclose(pose.R_pad_to_ned[:2, 0], heading)  # it faces where it drives


def test_a_rover_turning_steadily_drives_a_circle_and_a_wandering_one_both_ways():
    pad = {"motion": "rover", "height_m": 1.0, "speed_m_s": 3.0, "heading_deg": 0.0}
    circle = episode_world(scenario_with(pad={**pad, "turn_rate_deg_s": 6.0}), 0, 0).site
    radius = 3.0 / math.radians(6.0)
    centre = np.array([0.0, radius])  # heading north, turning right (clockwise from above)
    for t in np.linspace(0.0, 90.0, 31):
        pose = circle.pad_pose(float(t))
        assert np.linalg.norm(pose.position_ned[:2] - centre) == pytest.approx(radius, abs=1e-4)
        assert pose.omega_ned[2] == pytest.approx(math.radians(6.0), abs=1e-6)
    wander = episode_world(scenario_with(pad={**pad, "turn_rate_deg_s": [-8, 8]}), 0, 0).site
    rates = [wander.motion.turn_rate(float(t)) for t in np.linspace(0.0, 120.0, 600)]
    assert max(rates) <= math.radians(8) + 1e-12 and min(rates) >= -math.radians(8) - 1e-12
    assert max(rates) > 0.0 > min(rates)  # S-bends, not one long curve
    speeds = [np.linalg.norm(wander.pad_pose(float(t)).velocity_ned) for t in (5.0, 50.0, 80.0)]
    assert np.allclose(speeds, 3.0, atol=1e-5)


def test_a_deck_heaves_rolls_and_pitches_within_its_amplitudes_and_drifts():
    pad = {
        "motion": "deck",
        "height_m": 2.0,
        "speed_m_s": 0.5,
        "heading_deg": 90.0,
        "heave_m": 0.5,
        "roll_deg": 5.0,
        "pitch_deg": 3.0,
        "heave_period_s": [6.0, 8.0],
    }
    site = episode_world(scenario_with(pad=pad), 6, 2).site
    motion = site.motion
    assert isinstance(motion, DeckPad)
    samples = np.array([motion.motion(float(t)) for t in np.linspace(0.0, 300.0, 3001)])
    limits = (0.5, math.radians(5.0), math.radians(3.0))
    for column, limit in zip(samples.T, limits, strict=True):
        assert np.abs(column).max() <= limit + 1e-12
        assert np.abs(column).max() > 0.5 * limit  # it does move
    for t in (0.0, 4.2, 33.3):
        pose = site.pad_pose(t)
        heave = motion.motion(t)[0]
        assert np.allclose(pose.position_ned, [0.0, 0.5 * t, -(2.0 + heave)], atol=1e-9)
        dt = 1e-4
        rise = (motion.motion(t + dt)[0] - motion.motion(t - dt)[0]) / (2 * dt)
        assert pose.velocity_ned[2] == pytest.approx(-rise, abs=1e-5)


def test_ray_casts_meet_the_rover_roof_and_the_deck_at_their_time():
    rover = {"motion": "rover", "height_m": 1.5, "speed_m_s": 2.0, "heading_deg": 30.0}
    site = episode_world(scenario_with(pad=rover), 1, 0).site
    p = site.pad_pose(4.0).position_ned
    assert site.range_along((p[0], p[1], -10.0), (0, 0, 1), 4.0, 50.0) == pytest.approx(8.5)
    assert site.surface_height(p[0], p[1], 4.0) == pytest.approx(1.5)
    # at the start the rover is elsewhere: the same ray meets the ground
    assert site.range_along((p[0], p[1], -10.0), (0, 0, 1), 0.0, 50.0) == pytest.approx(10.0)
    assert site.surface_height(p[0], p[1], 0.0) == 0.0
    assert site.surface_height(p[0] + 12.0, p[1] - 12.0, 4.0) == 0.0
    deck = {"motion": "deck", "height_m": 2.0, "heave_m": 0.5, "roll_deg": 5.0, "pitch_deg": 4.0}
    site = episode_world(scenario_with(pad=deck), 2, 0).site
    for t in (0.0, 3.7, 11.2):
        centre = site.pad_pose(t).position_ned
        r = site.range_along((centre[0], centre[1], -20.0), (0, 0, 1), t, 50.0)
        assert r == pytest.approx(20.0 + centre[2], abs=1e-9)  # onto the deck at the pad
        assert site.surface_height(centre[0], centre[1], t) == pytest.approx(-centre[2])
    assert site.ground_height(30.0, 30.0) == 0.0  # the sea's mean level
    assert site.range_along((30.0, 30.0, -20.0), (0, 0, 1), 5.0, 50.0) == pytest.approx(20.0)


# --------------------------------------------------------------------------- drawn in flight


def test_the_camera_sees_the_pad_move_with_its_rover():
    pad = {"motion": "rover", "height_m": 1.5, "speed_m_s": 2.0, "heading_deg": 0.0}
    sc = scenario_with(visual={"terrain": ["asphalt"]}, pad=pad)
    w = episode_world(sc, 0, 0)
    v = w.visual
    fast = FastRenderer(v.ground(), v.pad(), w.site, v.sun)
    q = quat_from_euler(0.0, 0.0, 0.0)
    light = [float(np.mean(fast.render((0.0, 0.0, -15.0), q, CAMERA, t) > 120)) for t in (0, 5)]
    assert light[0] > 0.05 and light[1] < 0.5 * light[0]  # the pad has driven 10 m north
    ahead = fast.render((10.0, 0.0, -15.0), q, CAMERA, 5.0)
    assert np.mean(ahead > 120) == pytest.approx(light[0], rel=0.2)  # and is there, as bright
    still = scenario_with(visual={"terrain": ["asphalt"]}, terrain={"slope_deg": 5.0})
    w = episode_world(still, 0, 0)
    fast = FastRenderer(w.visual.ground(), w.visual.pad(), w.site, w.visual.sun)
    a, b = (fast.render((0.0, 0.0, -15.0), q, CAMERA, t) for t in (0.0, 5.0))
    assert np.array_equal(a, b)


def test_site_flights_are_deterministic_and_both_renderers_agree():
    sc = load_scenario("configs/sites/rover_fast.toml")
    fast_a, fast_b = flight_frames(sc, "fast", n=3), flight_frames(sc, "fast", n=3)
    assert all(np.array_equal(x, y) for x, y in zip(fast_a, fast_b, strict=True))
    ref = flight_frames(sc, "pybullet", n=3)
    for a, b in zip(ref, fast_a, strict=True):
        # same render, same sensor noise stream: only pixels on edges may differ
        assert np.mean(np.abs(a.astype(int) - b.astype(int)) > 40) < 0.01
