"""The live view: a flight as it happens, in Foxglove (``--live [HOST:]PORT``).

A :class:`LiveView` is a Foxglove WebSocket server (``foxglove-sdk``, the ``live`` extra; open
Foxglove, *Open connection*, ``ws://HOST:PORT``, and load ``docs/foxglove/visland.json``). Any
process that flies publishes one :class:`LiveFrame` per camera frame — the SITL (the truth), the
companion (what it sees and believes), ``visland log replay`` (a recorded flight) — on these
channels:

============================  ==========================  ====================================
topic                         schema                      what
============================  ==========================  ====================================
``/camera/image``             ``foxglove.RawImage``       the 128 px mono8 frame
``/camera/calibration``       ``foxglove.CameraCalibration``  its pinhole model (45 deg)
``/camera/annotations``       ``foxglove.ImageAnnotations``   the CNN's bearing and pad
                                                          probability; the estimator's pad
                                                          reprojected with its 2-sigma circle
``/scene``                    ``foxglove.SceneUpdate``    ground, pad, vehicle, trajectory,
                                                          camera frustum, the estimated pad and
                                                          its covariance, the wind
``/tf``                       ``foxglove.FrameTransforms``  ``ned`` -> ``pad``, ``vehicle``,
                                                          ``vehicle_level``; ``vehicle`` ->
                                                          ``camera`` (optical: z along body down)
``/live/state``               JSON                        time series: command, attitude,
                                                          radar range, estimate vs truth, link
                                                          counters, flight state
``/log``                      ``foxglove.Log``            state changes, failsafes (``/events``)
============================  ==========================  ====================================

Frames: ``ned`` is the world the source knows — the SITL's and a log's true NED (pad start at
the origin); the companion's is the pad-centred frame of its own estimate (the vehicle at the
estimated position). Times are the source's (sim time for the SITL and logs), in ns.

It costs nothing without a client: each part is built only when its channel has a subscriber
(``has_sinks``), and publishing never blocks — the SDK queues at most ``backlog`` messages per
client and drops the oldest for a slow one (a slow viewer loses frames, never setpoints).
"""

from companion.live.frame import (
    DEFAULT_LIVE_PORT,
    LiveFrame,
    live_frame,
    pad_extent_m,
    parse_live,
    with_truth,
)
from companion.live.view import LiveView

__all__ = [
    "DEFAULT_LIVE_PORT",
    "LiveFrame",
    "LiveView",
    "live_frame",
    "pad_extent_m",
    "parse_live",
    "with_truth",
]
