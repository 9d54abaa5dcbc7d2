"""The OpenCV camera source on a real video file (needs opencv-python-headless: the ``camera``
extra, in ``dev``).

A 320×240 video with a 60° horizontal field of view is rendered by the simulator's own scene
(the pad seen from a drifting, yawing vehicle at ~12 m), written with ``cv2.VideoWriter``
(MJPG, 30 fps), and opened as the companion opens a camera. What comes out must be what the
policy was trained on: 128×128 mono8 with a 45° field of view — the pad's apparent position
and size match a frame rendered directly at 128×128 / 45° from the same pose — at the policy's
10 Hz (every third frame of a 30 fps video).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from companion.camera import CameraError, OpenCvCameraSource, focal_px_from_fov
from companion.config import CompanionConfig, CompanionError, open_configured_camera
from sitl_sim.config import CameraConfig
from sitl_sim.physics.dynamics import quat_from_euler

cv2 = pytest.importorskip("cv2", reason="the camera extra: pip install 'visland[camera]'")

WIDTH_PX, HEIGHT_PX, HFOV_DEG, FPS = 320, 240, 60.0, 30.0
PAD_THRESHOLD = 118
"""Between the ground's brightest luma (82) and the pad's green (153) in the scene's render."""


def _poses(n: int):
    """A vehicle at ~12 m drifting towards the pad and yawing, slightly tilted."""
    return [
        (
            np.array([1.5 - 0.1 * k, -1.0 + 0.05 * k, -12.0 + 0.1 * k]),
            quat_from_euler(0.02, -0.03, 0.3 + 0.02 * k),
        )
        for k in range(n)
    ]


@pytest.fixture(scope="module")
def video(scene, tmp_path_factory):
    """(path, direct 128×128 45° renders of the same poses) of a 30-frame MJPG video."""
    # pybullet's fov is the vertical one: the 60° horizontal lens is 46.8° vertically at 4:3
    vfov = math.degrees(2 * math.atan(math.tan(math.radians(HFOV_DEG / 2)) * HEIGHT_PX / WIDTH_PX))
    wide = CameraConfig(WIDTH_PX, HEIGHT_PX, vfov, 0.0)
    policy_view = CameraConfig(128, 128, 45.0, 0.0)
    path = tmp_path_factory.mktemp("video") / "descent_320x240_60deg.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (WIDTH_PX, HEIGHT_PX))
    assert writer.isOpened(), "OpenCV cannot write MJPG here"
    direct = []
    for pos, quat in _poses(30):
        rgb = scene.render_rgb(pos, quat, wide)
        writer.write(np.ascontiguousarray(rgb[..., ::-1]))  # OpenCV writes BGR
        direct.append(scene.render(pos, quat, policy_view))
    writer.release()
    return path, direct


def _read_all(src: OpenCvCameraSource, timeout_s: float = 20.0):
    frames = []
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            frames += src.poll()
            if src.ended and not src._thread.is_alive():
                return frames + src.poll()
            time.sleep(0.005)
        raise AssertionError(f"{src.spec}: not at its end after {timeout_s} s")
    finally:
        src.close()


def _pad(img: np.ndarray) -> tuple[float, float, int, float]:
    """Pad centroid (column, row), pixel count and spread (std of its columns) in an image."""
    rows, cols = np.nonzero(img > PAD_THRESHOLD)
    assert len(rows) > 100, "no pad in the image"
    return float(cols.mean()), float(rows.mean()), len(rows), float(cols.std())


def test_a_60_degree_320x240_video_becomes_the_policy_45_degree_128px_view_at_10_hz(video):
    path, direct = video
    src = OpenCvCameraSource(str(path), hfov_deg=HFOV_DEG, realtime=False)
    assert src.frame_size_px == (WIDTH_PX, HEIGHT_PX) and src.fps == pytest.approx(FPS)
    assert src.fx_px == pytest.approx(focal_px_from_fov(WIDTH_PX, HFOV_DEG))
    frames = _read_all(src)
    # 30 fps decimated to the policy's 10 Hz: every third frame, none lost, none unreadable
    assert [f.frame_id for f in frames] == list(range(0, 30, 3))
    assert src.decimated == 20 and src.bad_frames == 0 and src.dropped == 0
    for f in frames:
        assert f.image.shape == (128, 128) and f.image.dtype == np.uint8
        col, row, n, spread = _pad(f.image)
        col0, row0, n0, spread0 = _pad(direct[f.frame_id])
        # where the pad is: the 45° crop's geometry (an off-centre pad moves with the focal
        # length); how big it is: the crop's scale. MJPG and area resampling blur the edges.
        assert abs(col - col0) < 0.75 and abs(row - row0) < 0.75, (f.frame_id, col, row)
        assert abs(n - n0) / n0 < 0.05, (f.frame_id, n, n0)
        assert abs(spread - spread0) / spread0 < 0.03, (f.frame_id, spread, spread0)
        # and the image itself: mono8 BT.601 luma of the same scene
        assert np.mean(np.abs(f.image.astype(int) - direct[f.frame_id])) < 3.0
    # intrinsics instead of the FOV: the same crop; rate None: every frame
    same = _read_all(
        OpenCvCameraSource(
            str(path), fx_px=focal_px_from_fov(WIDTH_PX, HFOV_DEG), rate_hz=None, realtime=False
        )
    )
    assert [f.frame_id for f in same] == list(range(30))
    assert all(np.array_equal(same[f.frame_id].image, f.image) for f in frames)


def test_a_file_plays_at_its_recorded_speed_and_the_config_opens_it(video):
    """Through the companion's own config → camera path: 30 frames at 30 fps take ~1 s and
    give every third frame, none before its recorded time on the companion clock."""
    path, _ = video
    cfg = CompanionConfig(camera=f"opencv:{path}", camera_hfov_deg=HFOV_DEG)
    src = open_configured_camera(cfg)
    assert isinstance(src, OpenCvCameraSource) and src.clock == "companion"
    t0 = time.monotonic()
    frames = _read_all(src)
    wall = time.monotonic() - t0
    assert [f.frame_id for f in frames] == list(range(0, 30, 3))
    # Recorded speed: a frame is handed on at its media time after the first, never earlier
    # (a loaded 2-core CI machine may wake the reader late, so lateness is not bounded here
    # except as a hang: the upper wall bound). 1 ms covers the clock read after the wait.
    t = np.array([f.time_s for f in frames]) - frames[0].time_s
    media = np.array([f.frame_id for f in frames]) / 30.0
    assert np.all(t >= media - 1e-3), (t, media)
    assert 0.85 <= wall <= 10.0, wall


def test_lens_and_source_errors_name_the_value_and_the_fix(video, tmp_path):
    path, _ = video
    # a 40° lens cannot give a 45° view: refused by the config, and by the source itself
    with pytest.raises(CompanionError, match=r"camera_hfov_deg = 40.0.*narrower.*45"):
        CompanionConfig(camera=f"opencv:{path}", camera_hfov_deg=40.0)
    with pytest.raises(CameraError, match=r"camera_hfov_deg = 40.0.*cannot be cropped"):
        OpenCvCameraSource(str(path), hfov_deg=40.0)
    # a focal length too long for this frame size: found on the first frame, at open
    with pytest.raises(CameraError, match=r"45.0° crop needs 497 px.*320x240.*too narrow"):
        OpenCvCameraSource(str(path), fx_px=600.0)
    # a principal point so far off-centre that the crop leaves the image
    with pytest.raises(CameraError, match="too narrow"):
        OpenCvCameraSource(str(path), hfov_deg=HFOV_DEG, cx_px=60.0)
    with pytest.raises(CompanionError, match="exactly one of camera_fx_px"):
        CompanionConfig(camera="opencv:0", camera_fx_px=500.0, camera_hfov_deg=62.2)
    with pytest.raises(CompanionError, match="exactly one of camera_fx_px"):
        CompanionConfig(camera="opencv:0", camera_hfov_deg=None)
    with pytest.raises(CameraError, match="does not exist"):
        OpenCvCameraSource(str(tmp_path / "missing.avi"), hfov_deg=HFOV_DEG)
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"not a video\n" * 100)
    with pytest.raises(CameraError, match=r"junk\.avi.*(could not open|no frame)"):
        OpenCvCameraSource(str(junk), hfov_deg=HFOV_DEG)
    with pytest.raises(CameraError, match="rate_hz"):
        OpenCvCameraSource(str(path), hfov_deg=HFOV_DEG, rate_hz=0.0)


def test_a_gstreamer_pipeline_without_gstreamer_in_opencv_says_which_opencv_to_install():
    from companion.camera import _has_gstreamer

    if _has_gstreamer(cv2):
        pytest.skip("this OpenCV has GStreamer")
    pipeline = "videotestsrc num-buffers=5 ! videoconvert ! appsink"
    with pytest.raises(CameraError, match=r"without GStreamer.*python3-opencv"):
        OpenCvCameraSource(pipeline, hfov_deg=62.2)
