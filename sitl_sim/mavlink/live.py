"""The SITL's live view (``visland sitl --live [HOST:]PORT``): the truth as it flies.

Each camera frame goes to a :class:`companion.live.LiveView` with the true vehicle, pad (moving
with its rover or deck), wind and the command the autopilot flies; a mode change is an event.
The companion's own view (what its CNN saw, its estimate) is ``visland companion --live``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from companion.live import LiveFrame, LiveView, parse_live, with_truth

if TYPE_CHECKING:
    from companion.contract import Command, GroundTruth
    from sitl_sim.simulator import CameraFrame

__all__ = ["SitlLive"]


class SitlLive:
    """The SITL's part that serves the live view (``address``: ``[HOST:]PORT``)."""

    def __init__(self, address: str) -> None:
        host, port = parse_live(address)
        self.view = LiveView(host, port, name="visland sitl")
        self._mode: str | None = None
        self.command: tuple[float, float, float, float] | None = None

    def flown(self, command: Command | None) -> None:
        """The command of this control period (None: motors off)."""
        self.command = (
            None
            if command is None
            else (command.thrust_norm, *(float(v) for v in command.rate_frd_rad_s))
        )

    def frame(
        self,
        frame: CameraFrame,
        truth: GroundTruth,
        mode: str,
        range_m: float,
        pad_size_m: tuple[float, float],
    ) -> None:
        """One camera frame (only built while a client watches); ``pad_size_m``: the episode's
        pad (:func:`companion.live.pad_extent_m`)."""
        if mode != self._mode:
            self.view.event(truth.time_s, f"mode {mode}")
            self._mode = mode
        if not self.view.watched:
            return
        live = LiveFrame(
            time_s=frame.exposure_time_s,
            image=frame.image,
            quat_wxyz=np.asarray(truth.quat_wxyz, float),
            pad_size_m=pad_size_m,
            command=self.command,
            range_m=range_m,
            state=mode,
        )
        self.view.publish(with_truth(live, truth))

    def close(self) -> None:
        self.view.close()
