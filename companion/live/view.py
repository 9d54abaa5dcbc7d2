"""The live view's server: :class:`LiveView`."""

from __future__ import annotations

import json
from collections import deque

from companion.live.frame import DEFAULT_LIVE_PORT, LiveFrame
from companion.live.messages import (
    TRAIL,
    camera_calibration,
    image_annotations,
    raw_image,
    scene_update,
    stamp,
    state_values,
    transforms,
)

__all__ = ["LiveView"]


class LiveView:
    """A Foxglove WebSocket server that shows :class:`LiveFrame` s (see the module docstring).

    Args:
        host, port: where to listen (port 0: any free one; :attr:`port` says which).
        name: the server's name in Foxglove.
        backlog: messages queued per client before the oldest are dropped.

    Raises:
        ImportError: foxglove-sdk is not installed (``pip install 'visland[live]'``).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = DEFAULT_LIVE_PORT,
        name: str = "visland",
        backlog: int = 64,
    ) -> None:
        try:
            import foxglove
            from foxglove import channels
        except ImportError as exc:
            raise ImportError("--live needs foxglove-sdk: pip install 'visland[live]'") from exc
        self._ctx = foxglove.Context()
        self._server = foxglove.start_server(
            name=name, host=host, port=port, context=self._ctx, message_backlog_size=backlog
        )
        ctx = self._ctx
        self._image = channels.RawImageChannel("/camera/image", context=ctx)
        self._calibration = channels.CameraCalibrationChannel("/camera/calibration", context=ctx)
        self._annotations = channels.ImageAnnotationsChannel("/camera/annotations", context=ctx)
        self._scene = channels.SceneUpdateChannel("/scene", context=ctx)
        self._tf = channels.FrameTransformsChannel("/tf", context=ctx)
        self._events = channels.LogChannel("/log", context=ctx)
        self._state = foxglove.Channel("/live/state", message_encoding="json", context=ctx)
        self._trail: deque[tuple[float, float, float]] = deque(maxlen=TRAIL)
        self.frames = 0
        """Frames offered (published or not)."""

    @property
    def port(self) -> int:
        """The port it listens on."""
        return int(self._server.port)

    @property
    def watched(self) -> bool:
        """Whether any client subscribes to any channel (else :meth:`publish` builds nothing)."""
        return any(
            c.has_sinks()
            for c in (
                self._image,
                self._calibration,
                self._annotations,
                self._scene,
                self._tf,
                self._events,
                self._state,
            )
        )

    def close(self) -> None:
        self._server.stop()

    # ------------------------------------------------------------------ publishing

    def event(self, time_s: float, text: str, error: bool = False) -> None:
        """A state change or a failsafe, on ``/log`` (a log's ``/events`` as ``foxglove.Log``)."""
        if not self._events.has_sinks():
            return
        from foxglove.messages import Log, LogLevel

        level = LogLevel.Error if error else LogLevel.Info
        self._events.log(
            Log(timestamp=stamp(time_s), level=level, message=text, name="visland"),
            log_time=self._ns(time_s),
        )

    def publish(self, f: LiveFrame) -> None:
        """One frame of every channel a client watches (nothing is built for the others)."""
        self.frames += 1
        if f.vehicle_pos_ned_m is not None:
            self._trail.append(tuple(float(v) for v in f.vehicle_pos_ned_m))
        ns = self._ns(f.time_s)
        if f.image is not None and self._image.has_sinks():
            self._image.log(raw_image(f), log_time=ns)
        if self._calibration.has_sinks():
            self._calibration.log(camera_calibration(f), log_time=ns)
        if self._annotations.has_sinks():
            self._annotations.log(image_annotations(f), log_time=ns)
        if self._tf.has_sinks():
            self._tf.log(transforms(f), log_time=ns)
        if self._scene.has_sinks():
            self._scene.log(scene_update(f, self._trail), log_time=ns)
        if self._state.has_sinks():
            self._state.log(json.dumps(state_values(f)).encode(), log_time=ns)

    @staticmethod
    def _ns(time_s: float) -> int:
        return max(0, round(time_s * 1e9))

    # ------------------------------------------------------------------ the parts
