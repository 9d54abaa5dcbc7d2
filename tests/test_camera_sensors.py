"""Camera conventions (image up = body forward, right = body right), radar, IMU, attitude."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.contract import Command
from sitl_sim.physics.dynamics import quat_from_euler
from sitl_sim.physics.sensors import RadarAltimeter
from sitl_sim.render.scene import Camera
from sitl_sim.scenario import InitialState
from sitl_sim.simulator import Simulator

CENTRE = 63.5  # pixel centres run 0..127


def _pad_centroid(scene, cfg, pos_ned, euler=(0.0, 0.0, 0.0)) -> tuple[float, float]:
    """(row, col) centroid of the pad's pixels (green square or red cross) in a render."""
    rgb = scene.render_rgb(np.asarray(pos_ned, float), quat_from_euler(*euler), cfg).astype(int)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    pad = ((g > 150) & (r < 120) & (b < 120)) | ((r > 150) & (g < 60) & (b < 60))
    assert pad.sum() > 10, "pad not visible"
    rows, cols = np.nonzero(pad)
    return float(rows.mean()), float(cols.mean())


def _focal(cfg) -> float:
    return 0.5 * cfg.height_px / math.tan(math.radians(cfg.fov_deg) / 2)


def test_level_over_the_pad_sees_it_centred(scene, sim_cfg):
    row, col = _pad_centroid(scene, sim_cfg.camera, (0.0, 0.0, -50.0))
    assert abs(row - CENTRE) <= 2 and abs(col - CENTRE) <= 2


def test_pad_north_at_yaw_zero_is_above_centre_at_the_pinhole_offset(scene, sim_cfg):
    row, col = _pad_centroid(scene, sim_cfg.camera, (-10.0, 0.0, -50.0))  # pad 10 m north
    assert row == pytest.approx(CENTRE - _focal(sim_cfg.camera) * 10 / 50, abs=2)
    assert abs(col - CENTRE) <= 2


def test_pad_east_is_right_of_centre(scene, sim_cfg):
    row, col = _pad_centroid(scene, sim_cfg.camera, (0.0, -10.0, -50.0))  # pad 10 m east
    assert col == pytest.approx(CENTRE + _focal(sim_cfg.camera) * 10 / 50, abs=2)
    assert abs(row - CENTRE) <= 2


def test_heading_east_puts_a_pad_to_the_north_on_the_left(scene, sim_cfg):
    row, col = _pad_centroid(scene, sim_cfg.camera, (-10.0, 0.0, -50.0), (0, 0, math.pi / 2))
    assert col < CENTRE - 20 and abs(row - CENTRE) <= 2


def test_positive_roll_tilts_the_view_as_a_downward_camera(scene, sim_cfg):
    # Right wing down: the camera axis swings to the left, so a pad straight below moves right
    # by f * tan(roll).
    roll = 0.1
    row, col = _pad_centroid(scene, sim_cfg.camera, (0.0, 0.0, -50.0), (roll, 0.0, 0.0))
    assert col == pytest.approx(CENTRE + _focal(sim_cfg.camera) * math.tan(roll), abs=2)
    assert abs(row - CENTRE) <= 2


def test_positive_pitch_moves_the_pad_down_the_image(scene, sim_cfg):
    # Nose up: the camera looks ahead, so the pad below appears towards the image bottom.
    row, col = _pad_centroid(scene, sim_cfg.camera, (0.0, 0.0, -50.0), (0.0, 0.1, 0.0))
    assert abs(col - CENTRE) <= 2
    assert row == pytest.approx(CENTRE + _focal(sim_cfg.camera) * math.tan(0.1), abs=2)


def test_camera_image_is_mono8_with_seeded_noise(scene, sim_cfg):
    q = quat_from_euler(0, 0, 0)
    pos = np.array([1.0, 2.0, -40.0])
    imgs = [
        Camera(scene, sim_cfg.camera, np.random.default_rng(s)).capture(pos, q) for s in (1, 1, 2)
    ]
    assert imgs[0].shape == (128, 128) and imgs[0].dtype == np.uint8
    np.testing.assert_array_equal(imgs[0], imgs[1])
    assert not np.array_equal(imgs[0], imgs[2])
    clean = scene.render(pos, q, sim_cfg.camera)
    diff = imgs[0].astype(float) - clean
    assert diff.std() == pytest.approx(sim_cfg.camera.noise_std_px, rel=0.2)


def test_pad_green_is_brighter_and_cross_darker_than_the_ground_in_mono8(scene, sim_cfg):
    # The paper's pad must stand out after the mono8 conversion the policy sees.
    pos, q = np.array([0.0, 0.0, -10.0]), quat_from_euler(0, 0, 0)
    img = scene.render(pos, q, sim_cfg.camera).astype(int)
    rgb = scene.render_rgb(pos, q, sim_cfg.camera).astype(int)
    green = (rgb[..., 1] > 150) & (rgb[..., 0] < 120)
    red = (rgb[..., 0] > 150) & (rgb[..., 1] < 60)
    far = scene.render(np.array([0.0, 0.0, -120.0]), q, sim_cfg.camera).astype(int)
    ground = far[:16, :]  # 120 m up, the image border is all terrain
    assert green.sum() > 100 and red.sum() > 100
    assert img[green].min() > ground.max()
    assert img[red].max() < img[green].min() - 40


@pytest.mark.parametrize("tilt_deg", [0.0, 10.0, 25.0])
def test_radar_reads_altitude_over_cos_tilt(sim_cfg, tilt_deg):
    radar = RadarAltimeter(sim_cfg.radar, np.random.default_rng(0))
    q = quat_from_euler(math.radians(tilt_deg), 0.0, 0.7)
    readings = np.array([radar.read((3.0, 4.0, -60.0), q) for _ in range(200)])
    expected = 60.0 / math.cos(math.radians(tilt_deg))
    sigma = sim_cfg.radar.noise_std_m + sim_cfg.radar.noise_fraction * expected
    assert abs(readings.mean() - expected) < 4 * sigma / math.sqrt(200)
    assert readings.std() == pytest.approx(sigma, rel=0.2)


def test_radar_is_invalid_beyond_range_or_pointing_away(sim_cfg):
    radar = RadarAltimeter(sim_cfg.radar, np.random.default_rng(0))
    assert math.isnan(radar.read((0, 0, -151.0), quat_from_euler(0, 0, 0)))
    assert math.isnan(radar.read((0, 0, -140.0), quat_from_euler(math.radians(30), 0, 0)))
    assert math.isnan(radar.read((0, 0, -10.0), quat_from_euler(math.radians(95), 0, 0)))
    assert not math.isnan(radar.read((0, 0, -149.0), quat_from_euler(0, 0, 0)))


def test_imu_reads_minus_g_at_hover_and_on_the_ground(vehicle, sim_cfg):
    sim = Simulator(vehicle, sim_cfg, render=False)
    for alt in (30.0, 0.0):
        sim.reset(InitialState((0, 0, -alt), (0, 0, 0), (0, 0, 0), (0, 0, 0)), seed=3)
        hover = Command(vehicle.hover_thrust_norm(sim_cfg.planet), np.zeros(3))
        acc = []
        for _ in range(20):
            sim.step(hover if alt > 0 else None)
            acc.append(sim.observe().accel_frd_m_s2)
        mean = np.mean(acc, axis=0)
        np.testing.assert_allclose(mean, [0.0, 0.0, -9.81], atol=0.05)


def test_attitude_estimate_tracks_truth(vehicle, sim_cfg):
    sim = Simulator(vehicle, sim_cfg, render=False)
    euler = (0.05, -0.03, 2.0)
    sim.reset(InitialState((0, 0, -30), (0, 0, 0), euler, (0, 0, 0)), seed=1)
    obs = sim.observe()
    np.testing.assert_allclose(
        obs.attitude_rad, euler, atol=5 * sim_cfg.attitude.angle_noise_std_rad
    )
