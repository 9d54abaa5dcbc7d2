"""Camera sources behind one interface: what the policy sees is always a 128×128 mono8 image
with a 45° full field of view, row 0 = body forward, column 0 = body left.

* :class:`UdpCameraSource` — the SITL's (or a camera bridge's) UDP frames
  (:mod:`companion.contract.camera_packet`); time stamps on the autopilot's boot clock.
* :class:`OpenCvCameraSource` — a real camera: an OpenCV device index, a video file or a
  GStreamer pipeline. Each frame is turned to mono8, centre-cropped to the 45° field of view
  given the camera's focal length (from intrinsics ``fx`` or its horizontal FOV), rotated for
  the mounting and resized to 128×128 (:func:`fit_to_policy`); frames are handed on at the
  policy's control rate (10 Hz). Time stamps on the companion's monotonic clock.
* :class:`McapReplaySource` — the frames of a flight log (``/camera/image``), paced as recorded
  or as fast as they are read.

``poll()`` never blocks; ``fileno()`` gives what to ``select`` on. A malformed datagram or an
unreadable frame is counted and skipped, never raised into the flight loop.
"""

from __future__ import annotations

import base64
import math
import os
import queue
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

import numpy as np

from companion.contract import CAMERA_FOV_DEG, IMAGE_SIZE_PX
from companion.contract.camera_packet import CameraPacketError, FrameAssembler
from companion.contract.datagrams import RCVBUF_BYTES, RX_DATAGRAMS_PER_POLL

__all__ = [
    "RESTART_WINDOW_S",
    "CameraError",
    "CameraSource",
    "McapReplaySource",
    "OpenCvCameraSource",
    "ReceivedFrame",
    "UdpCameraSource",
    "check_intrinsics",
    "fit_to_policy",
    "focal_px_from_fov",
    "open_camera",
]

Clock = Literal["autopilot", "companion"]

RESTART_WINDOW_S = 1.0
"""A SITL frame stamped this much before the newest one is from a restarted source, not a late
datagram (as :class:`companion.link.MavlinkLink` tells a restart from ``time_boot_ms``)."""


class CameraError(Exception):
    """A camera source cannot be opened or is configured wrongly (names the source/value)."""


@dataclass(frozen=True)
class ReceivedFrame:
    """One frame as the companion received it.

    Attributes:
        frame_id: the source's frame counter.
        time_s: capture time on the source's clock (``CameraSource.clock``).
        image: (128, 128) uint8 mono8.
        rx_s: companion monotonic time when the frame was complete.
    """

    frame_id: int
    time_s: float
    image: np.ndarray
    rx_s: float


class CameraSource(Protocol):
    """What the flight loop needs from a camera."""

    clock: Clock
    """``autopilot``: ``time_s`` is on the autopilot's boot clock (SITL frames); ``companion``:
    on the companion's monotonic clock (a local camera)."""

    def fileno(self) -> int | None:
        """A descriptor that becomes readable when a frame may be ready (None: poll)."""
        ...

    def poll(self) -> list[ReceivedFrame]:
        """Frames completed since the last call, oldest first (never blocks)."""
        ...

    def close(self) -> None: ...


# --------------------------------------------------------------------------- geometry


def focal_px_from_fov(width_px: int, hfov_deg: float) -> float:
    """Focal length in pixels of a pinhole camera ``width_px`` wide with horizontal FOV."""
    if not 0.0 < hfov_deg < 180.0:
        raise CameraError(f"hfov_deg = {hfov_deg}; expected in (0, 180)")
    return (width_px / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)


def _resize_area(img: np.ndarray, size: int) -> np.ndarray:
    """Area-average resize of a square uint8 image to ``size``×``size`` (numpy only)."""
    n = img.shape[0]
    if n == size:
        return img
    edges = np.linspace(0, n, size + 1)
    # Integral image: every output pixel is the mean of its (fractional) input box.
    integ = np.zeros((n + 1, n + 1))
    integ[1:, 1:] = np.cumsum(np.cumsum(img.astype(np.float64), axis=0), axis=1)

    def interp(arr: np.ndarray, pos: np.ndarray, axis: int) -> np.ndarray:
        lo = np.floor(pos).astype(int)
        hi = np.minimum(lo + 1, n)
        frac = pos - lo
        a = np.take(arr, lo, axis=axis)
        b = np.take(arr, hi, axis=axis)
        shape = [1, 1]
        shape[axis] = -1
        return a + (b - a) * frac.reshape(shape)

    rows = interp(integ, edges, 0)  # (size+1, n+1)
    box = interp(rows, edges, 1)  # (size+1, size+1)
    sums = box[1:, 1:] - box[:-1, 1:] - box[1:, :-1] + box[:-1, :-1]
    area = np.outer(np.diff(edges), np.diff(edges))
    return np.clip(np.rint(sums / area), 0, 255).astype(np.uint8)


def fit_to_policy(
    image: np.ndarray,
    fx_px: float,
    *,
    cx_px: float | None = None,
    cy_px: float | None = None,
    rotate_deg: int = 0,
    fov_deg: float = CAMERA_FOV_DEG,
    size_px: int = IMAGE_SIZE_PX,
) -> np.ndarray:
    """A camera image -> the policy's (size, size) mono8 image with a ``fov_deg`` full FOV.

    The square crop centred on the principal point (cx, cy; default the image centre) spans
    ``2 fx tan(fov/2)`` pixels — the pinhole geometry of a ``fov_deg`` camera — and is then
    rotated by ``rotate_deg`` (counter-clockwise, a multiple of 90, so that the image top is
    body forward) and area-resized.

    Args:
        image: (H, W) mono8, or (H, W, 3) BGR (OpenCV's order), uint8.
        fx_px: focal length in pixels (the camera matrix's ``fx``; square pixels assumed).

    Raises:
        CameraError: the camera's field of view is narrower than ``fov_deg``, or bad input.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise CameraError(f"image: expected uint8 (H, W) or (H, W, 3), got {img.shape} {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] != 3:
            raise CameraError(f"image: expected 3 channels (BGR), got {img.shape[2]}")
        # BT.601 luma, as the simulator's camera (DESIGN.md: mono8 = BT.601 luma)
        b, g, r = (img[..., k].astype(np.float32) for k in range(3))
        img = np.clip(np.rint(0.299 * r + 0.587 * g + 0.114 * b), 0, 255).astype(np.uint8)
    if rotate_deg % 90 != 0:
        raise CameraError(f"rotate_deg = {rotate_deg}; expected a multiple of 90")
    if not (math.isfinite(fx_px) and fx_px > 0):
        raise CameraError(f"fx_px = {fx_px}; expected > 0")
    h, w = img.shape
    cx = (w - 1) / 2.0 if cx_px is None else cx_px
    cy = (h - 1) / 2.0 if cy_px is None else cy_px
    side = 2.0 * fx_px * math.tan(math.radians(fov_deg) / 2.0)
    n = round(side)
    x0 = round(cx - (n - 1) / 2.0)
    y0 = round(cy - (n - 1) / 2.0)
    if n < 1 or x0 < 0 or y0 < 0 or x0 + n > w or y0 + n > h:
        raise CameraError(
            f"a {fov_deg}° crop needs {side:.0f} px around ({cx:.0f}, {cy:.0f}) but the image is "
            f"{w}x{h}: the camera's field of view is too narrow (use a wider lens)"
        )
    crop = img[y0 : y0 + n, x0 : x0 + n]
    crop = np.rot90(crop, k=(rotate_deg // 90) % 4)
    return np.ascontiguousarray(_resize_area(np.ascontiguousarray(crop), size_px))


# --------------------------------------------------------------------------- UDP (SITL)


class UdpCameraSource:
    """Camera packets on a UDP port (the SITL sends to 127.0.0.1:5600 by default).

    Counts ``bad_packets`` (malformed datagrams), ``bad_size`` (frames that are not 128×128
    mono8: refused, the policy's contract cannot take them) and ``stale_frames`` (a frame
    stamped at or before the newest delivered one: a duplicate or a reordered datagram of a
    lossy link; answering it would step the policy twice, or backwards in time). A frame
    stamped more than :data:`RESTART_WINDOW_S` before the newest is a restarted source (a new
    SITL, its clock from zero) and is delivered: the MAVLink link's restart rule.
    """

    clock: Clock = "autopilot"

    def __init__(self, host: str = "127.0.0.1", port: int = 5600) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        try:
            self.sock.bind((host, port))
        except OSError as exc:
            self.sock.close()
            raise CameraError(f"camera udp:{host}:{port}: cannot bind: {exc}") from None
        self.sock.setblocking(False)
        self.address = self.sock.getsockname()
        self._assembler = FrameAssembler()
        self._newest_time_s = -math.inf
        self.bad_packets = 0
        self.bad_size = 0
        self.stale_frames = 0
        self.deferred = 0

    def fileno(self) -> int | None:
        return self.sock.fileno()

    def poll(self) -> list[ReceivedFrame]:
        """The frames the waiting datagrams complete, oldest first: at most
        :data:`~companion.contract.datagrams.RX_DATAGRAMS_PER_POLL` datagrams (``deferred``
        counts the polls that stopped there), so a flood on the camera's port delays the
        companion's loop but never holds it from its MAVLink link."""
        out: list[ReceivedFrame] = []
        for _ in range(RX_DATAGRAMS_PER_POLL):
            try:
                data = self.sock.recv(65_535)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                return out
            try:
                frame = self._assembler.add(data)
            except CameraPacketError:
                self.bad_packets += 1
                continue
            if frame is None:
                continue
            if frame.image.shape != (IMAGE_SIZE_PX, IMAGE_SIZE_PX):
                self.bad_size += 1
                continue
            newest = self._newest_time_s
            if newest - RESTART_WINDOW_S <= frame.time_s <= newest:
                self.stale_frames += 1
                continue
            self._newest_time_s = frame.time_s
            out.append(ReceivedFrame(frame.frame_id, frame.time_s, frame.image, time.monotonic()))
        self.deferred += 1  # the budget is spent; the rest waits for the next poll
        return out

    def counters(self) -> dict[str, int]:
        """What was refused: malformed datagrams, wrong-size frames, incomplete frames evicted,
        frames whose CRC failed (the companion's report, ``camera``)."""
        return {
            "bad_packets": self.bad_packets,
            "bad_size": self.bad_size,
            "incomplete_dropped": self._assembler.dropped,
            "corrupt": self._assembler.corrupt,
            "deferred": self.deferred,
        }

    def close(self) -> None:
        self.sock.close()


# --------------------------------------------------------------------------- OpenCV


def check_intrinsics(fx_px: float | None, hfov_deg: float | None) -> None:
    """Check a real camera's lens description before any frame is read.

    Exactly one of ``fx_px`` (focal length in pixels, from a calibration) or ``hfov_deg`` (the
    lens' horizontal field of view) is given; a horizontal FOV must be wider than the policy's
    45° (the crop cannot invent pixels). Whether an ``fx`` fits is known only with the frame
    size (:func:`fit_to_policy` on the first frame).

    Raises:
        CameraError: naming the value and what was expected.
    """
    if (fx_px is None) == (hfov_deg is None):
        raise CameraError(
            "give exactly one of camera_fx_px (intrinsics, pixels) or camera_hfov_deg (lens "
            f"FOV), got fx_px = {fx_px}, hfov_deg = {hfov_deg}"
        )
    if fx_px is not None and not (math.isfinite(fx_px) and fx_px > 0):
        raise CameraError(f"camera_fx_px = {fx_px}; expected a focal length > 0 px")
    if hfov_deg is not None:
        if not (math.isfinite(hfov_deg) and 0.0 < hfov_deg < 180.0):
            raise CameraError(f"camera_hfov_deg = {hfov_deg}; expected in (0, 180)")
        if hfov_deg <= CAMERA_FOV_DEG:
            raise CameraError(
                f"camera_hfov_deg = {hfov_deg}: a lens narrower than the policy's "
                f"{CAMERA_FOV_DEG:g}° field of view cannot be cropped to it (use a wider lens)"
            )


def _has_gstreamer(cv2) -> bool:
    for line in cv2.getBuildInformation().splitlines():
        if line.strip().startswith("GStreamer:"):
            return "YES" in line
    return False


class OpenCvCameraSource:
    """A real camera through OpenCV (``opencv-python-headless``, the ``camera`` extra):
    device index, video file or GStreamer pipeline. A reader thread grabs frames, hands the
    policy one every ``1 / rate_hz`` seconds (its control period: a 30 fps camera is decimated
    to 10 Hz, the rate the LSTM and the estimator were trained at) and ``poll`` returns them.

    The first frame is read when the source opens, so a camera that gives nothing, or whose
    field of view cannot hold the 45° crop, fails here with a :class:`CameraError` instead of
    silently never delivering a frame.

    Args:
        spec: ``"0"`` (device index), a file path, or a GStreamer pipeline (contains ``!``,
            needs an OpenCV built with GStreamer: the distribution's ``python3-opencv``; the
            pip wheels have none).
        fx_px: focal length in pixels (camera matrix ``fx``); or give ``hfov_deg``.
        hfov_deg: the camera's horizontal field of view, when intrinsics are not known.
        cx_px / cy_px: principal point (default: image centre).
        rotate_deg: mounting rotation so the image top is body forward (multiple of 90).
        rate_hz: frames handed on per second (None: every frame). Decimation follows the
            capture time: the wall clock for a device or pipeline, the media time for a file.
        realtime: a file plays at its recorded speed (False: as fast as it decodes, no frame
            dropped — for tests and offline checks). Devices and pipelines are live anyway.
        loop: restart a video file at its end (bench/demo).

    Counters: ``bad_frames`` (unreadable or unfit frames), ``dropped`` (live frames the flight
    loop did not take in time), ``decimated`` (frames skipped for ``rate_hz``); ``ended`` when
    a file (or a device) stopped giving frames.
    """

    clock: Clock = "companion"

    def __init__(
        self,
        spec: str,
        *,
        fx_px: float | None = None,
        hfov_deg: float | None = None,
        cx_px: float | None = None,
        cy_px: float | None = None,
        rotate_deg: int = 0,
        rate_hz: float | None = 10.0,
        realtime: bool = True,
        loop: bool = False,
    ) -> None:
        try:
            import cv2  # optional: pip install 'visland[camera]' (opencv-python-headless)
        except ImportError:
            raise CameraError(
                f"camera {spec!r}: OpenCV is not installed (pip install 'visland[camera]', i.e. "
                "opencv-python-headless; on a Pi/Jetson: apt install python3-opencv)"
            ) from None
        try:
            check_intrinsics(fx_px, hfov_deg)
        except CameraError as exc:
            raise CameraError(f"camera {spec!r}: {exc}") from None
        if rotate_deg % 90 != 0:
            raise CameraError(f"camera {spec!r}: rotate_deg = {rotate_deg}; a multiple of 90")
        if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
            raise CameraError(f"camera {spec!r}: rate_hz = {rate_hz}; expected > 0 (or None)")
        self._cv2 = cv2
        self.live = spec.isdigit() or "!" in spec
        if spec.isdigit():
            cap = cv2.VideoCapture(int(spec))
        elif "!" in spec:
            if not _has_gstreamer(cv2):
                raise CameraError(
                    f"camera {spec!r}: a GStreamer pipeline, but this OpenCV "
                    f"({cv2.__version__}) is built without GStreamer (the pip wheels are); "
                    "install the distribution's python3-opencv"
                )
            cap = cv2.VideoCapture(spec, cv2.CAP_GSTREAMER)
        else:
            if not Path(spec).is_file():
                raise CameraError(f"camera file {spec!r} does not exist")
            cap = cv2.VideoCapture(spec)
        if not cap.isOpened():
            raise CameraError(f"camera {spec!r}: OpenCV could not open it")
        self.spec = spec
        self._cap = cap
        self._cx, self._cy, self._rot = cx_px, cy_px, rotate_deg
        self._period = None if rate_hz is None else 1.0 / rate_hz
        self._realtime = realtime and not self.live
        self._loop = loop and not self.live
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = fps if math.isfinite(fps) and 0 < fps < 1000 else 30.0
        ok, first = cap.read()
        if not ok or first is None:
            cap.release()
            raise CameraError(f"camera {spec!r}: opened, but no frame could be read")
        self.frame_size_px = (int(first.shape[1]), int(first.shape[0]))
        self.fx_px = fx_px if fx_px is not None else focal_px_from_fov(first.shape[1], hfov_deg)
        try:
            self._fit(first)
        except CameraError as exc:
            cap.release()
            raise CameraError(f"camera {spec!r}: {exc}") from None
        self._first = first
        self._queue: queue.Queue[ReceivedFrame] = queue.Queue(maxsize=4)
        self._rfd, self._wfd = os.pipe()
        os.set_blocking(self._rfd, False)
        self._stop = threading.Event()
        self.bad_frames = 0
        self.dropped = 0
        self.decimated = 0
        self.ended = False
        self._thread = threading.Thread(target=self._reader, daemon=True, name="camera")
        self._thread.start()

    def _fit(self, raw: np.ndarray) -> np.ndarray:
        return fit_to_policy(raw, self.fx_px, cx_px=self._cx, cy_px=self._cy, rotate_deg=self._rot)

    def _media_time_s(self, index: int) -> float:
        """A file frame's media time (container timestamps; ``index / fps`` if it has none)."""
        ms = float(self._cap.get(self._cv2.CAP_PROP_POS_MSEC) or 0.0)
        return ms / 1000.0 if ms > 0 or index == 0 else index / self.fps

    def _put(self, frame: ReceivedFrame) -> bool:
        """Hand a frame on: a live camera drops the oldest waiting one, a file waits."""
        while not self._stop.is_set():
            if self.live and self._queue.full():
                try:
                    self._queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass
            try:
                self._queue.put(frame, timeout=0.05)
            except queue.Full:
                continue
            os.write(self._wfd, b"x")
            return True
        return False

    def _reader(self) -> None:
        frame_id = 0  # frames read (the id a frame keeps, decimated or not)
        raw: np.ndarray | None = self._first
        self._first = None
        start_wall = time.monotonic()
        offset_s = 0.0  # media time of a looped file keeps increasing
        last_media = 0.0
        next_due: float | None = None
        while not self._stop.is_set():
            if raw is None:
                ok, raw = self._cap.read()
                if not ok or raw is None:
                    if self._loop:
                        self._cap.set(self._cv2.CAP_PROP_POS_FRAMES, 0)
                        offset_s = last_media + 1.0 / self.fps
                        raw = None
                        continue
                    self.ended = True
                    return
            rx = time.monotonic()
            t = rx if self.live else offset_s + self._media_time_s(frame_id)
            last_media = t
            if self._realtime:  # play a file at its recorded speed
                delay = start_wall + t - rx
                if delay > 0 and self._stop.wait(delay):
                    return
                rx = time.monotonic()
            take = True
            if self._period is not None:
                # a frame is due every period; accept one a little early (a quarter of a
                # camera frame interval) so 30 fps -> 10 Hz takes every third frame on jitter
                slack = 0.25 / self.fps
                if next_due is not None and t < next_due - slack:
                    take = False
                else:
                    next_due = t + self._period if next_due is None else next_due + self._period
                    if next_due < t - self._period:  # fell behind (a stall): resynchronise
                        next_due = t + self._period
            if not take:
                self.decimated += 1
            else:
                try:
                    image = self._fit(raw)
                except CameraError:
                    self.bad_frames += 1
                else:
                    if not self._put(ReceivedFrame(frame_id, rx, image, rx)):
                        return
            frame_id += 1
            raw = None

    def fileno(self) -> int | None:
        return self._rfd

    def poll(self) -> list[ReceivedFrame]:
        try:
            os.read(self._rfd, 4096)
        except BlockingIOError:
            pass
        out = []
        while True:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._cap.release()
        for fd in (self._rfd, self._wfd):
            try:
                os.close(fd)
            except OSError:
                pass


# --------------------------------------------------------------------------- MCAP replay


class McapReplaySource:
    """The frames of a flight log (``/camera/image``), oldest first.

    Args:
        path: an MCAP flight log (companion or SITL).
        realtime: pace frames by their recorded times (False: all at once, as fast as read).
        clock_fn: monotonic clock (injectable).
    """

    clock: Clock = "autopilot"

    def __init__(
        self,
        path: str | Path,
        *,
        realtime: bool = True,
        clock_fn: Callable[[], float] = time.monotonic,
    ) -> None:
        from companion.contract.topics import TOPIC_IMAGE
        from companion.flightlog import FlightLogError, read_log

        try:
            log = read_log(path, topics=[TOPIC_IMAGE])
        except FlightLogError as exc:
            raise CameraError(str(exc)) from None
        self._frames: list[tuple[int, float, np.ndarray]] = []
        for msg in log.topic(TOPIC_IMAGE):
            img = np.frombuffer(base64.b64decode(msg["data"]), dtype=np.uint8)
            if msg.get("width") != IMAGE_SIZE_PX or msg.get("height") != IMAGE_SIZE_PX:
                continue
            fid = str(msg.get("frame_id", "0")).rsplit("/", 1)[-1]
            t = float(msg.get("capture_time_s", msg["time_s"]))
            self._frames.append((int(fid) if fid.isdigit() else 0, t, img.reshape(128, 128)))
        if not self._frames:
            raise CameraError(f"{path}: no 128x128 frames on {TOPIC_IMAGE}")
        self._realtime = realtime
        self._clock = clock_fn
        self._t0: float | None = None
        self._next = 0

    def fileno(self) -> int | None:
        return None

    @property
    def exhausted(self) -> bool:
        return self._next >= len(self._frames)

    def poll(self) -> list[ReceivedFrame]:
        now = self._clock()
        if self._t0 is None:
            self._t0 = now - self._frames[0][1]
        out = []
        while self._next < len(self._frames):
            fid, t, img = self._frames[self._next]
            if self._realtime and self._t0 + t > now:
                break
            out.append(ReceivedFrame(fid, t, img, now))
            self._next += 1
        return out

    def close(self) -> None:
        self._frames = []


def open_camera(spec: str, **opencv_options) -> CameraSource:
    """A camera from a spec string: ``udp:HOST:PORT`` (SITL frames), ``mcap:PATH`` (replay),
    ``opencv:DEVICE|FILE|PIPELINE``."""
    kind, _, rest = spec.partition(":")
    if kind == "udp":
        host, _, port = rest.rpartition(":")
        if not port.isdigit():
            raise CameraError(f"camera {spec!r}: expected udp:HOST:PORT")
        return UdpCameraSource(host or "127.0.0.1", int(port))
    if kind == "mcap":
        return McapReplaySource(rest)
    if kind == "opencv":
        return OpenCvCameraSource(rest, **opencv_options)
    raise CameraError(f"camera {spec!r}: expected udp:HOST:PORT, mcap:PATH or opencv:SPEC")
