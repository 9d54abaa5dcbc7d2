"""The Foxglove messages of a :class:`~companion.live.frame.LiveFrame` (foxglove-sdk's typed
messages; imported when a message is built, so the module loads without the SDK)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from companion.contract import CAMERA_FOV_DEG, IMAGE_SIZE_PX
from companion.contract.messages import quat_to_rotation
from companion.live.frame import LiveFrame, _float

__all__ = [
    "TRAIL",
    "camera_calibration",
    "decoded",
    "frame_stamp",
    "image_annotations",
    "protobuf_decoder",
    "raw_image",
    "scene_update",
    "stamp",
    "stamp_ns",
    "state_values",
    "transforms",
]

TRAIL = 600
"""Trajectory points kept (60 s of 10 Hz frames)."""
_FOCAL_PX = 0.5 * IMAGE_SIZE_PX / math.tan(math.radians(CAMERA_FOV_DEG) / 2)
# the camera's optical frame (x image right, y image down, z along the view) in body FRD:
# image right = body right, image down = body backward, the view = body down
_BODY_TO_OPTICAL_QUAT = (0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5))  # (x, y, z, w): yaw +90 deg


def protobuf_decoder(schema_name: str, descriptor_set: bytes):
    """``data -> message`` for the protobuf schema ``schema_name`` whose FileDescriptorSet is
    ``descriptor_set`` (as a Foxglove channel advertises it, or an MCAP schema record holds it;
    ``protobuf``, in the ``live`` extra)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(descriptor_set)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name)).FromString


def decoded(msg: Any) -> Any:
    """A foxglove-sdk message (write-only) as the protobuf message it encodes to: what a client
    reads from the wire or a file."""
    schema = type(msg).get_schema()
    return protobuf_decoder(schema.name, bytes(schema.data))(msg.encode())


def stamp(time_s: float) -> Any:
    from foxglove.messages import Timestamp

    sec = math.floor(time_s)
    return Timestamp(int(sec), round((time_s - sec) * 1e9) % 1_000_000_000)


def stamp_ns(ns: int) -> Any:
    """An exact stamp of ``ns`` nanoseconds (a file's clock, where float seconds round)."""
    from foxglove.messages import Timestamp

    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def frame_stamp(f: LiveFrame) -> Any:
    """The stamp of ``f``'s messages: its ``stamp_ns`` if it has one, else its time."""
    return stamp(f.time_s) if f.stamp_ns is None else stamp_ns(f.stamp_ns)


def _vec(v) -> Any:
    from foxglove.messages import Vector3

    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(q_wxyz) -> Any:
    from foxglove.messages import Quaternion

    w, x, y, z = (float(a) for a in q_wxyz)
    return Quaternion(x=x, y=y, z=z, w=w)


def _pose(pos=(0.0, 0.0, 0.0), q_wxyz=(1.0, 0.0, 0.0, 0.0)) -> Any:
    from foxglove.messages import Pose

    return Pose(position=_vec(pos), orientation=_quat(q_wxyz))


def _color(r: float, g: float, b: float, a: float = 1.0) -> Any:
    from foxglove.messages import Color

    return Color(r=r, g=g, b=b, a=a)


def raw_image(f: LiveFrame) -> Any:
    from foxglove.messages import RawImage

    img = np.ascontiguousarray(f.image, dtype=np.uint8)
    return RawImage(
        timestamp=frame_stamp(f),
        frame_id="camera",
        width=int(img.shape[1]),
        height=int(img.shape[0]),
        encoding="mono8",
        step=int(img.shape[1]),
        data=img.tobytes(),
    )


def camera_calibration(f: LiveFrame) -> Any:
    from foxglove.messages import CameraCalibration

    n, fx = IMAGE_SIZE_PX, _FOCAL_PX
    c = n / 2
    return CameraCalibration(
        timestamp=frame_stamp(f),
        frame_id="camera",
        width=n,
        height=n,
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[fx, 0.0, c, 0.0, fx, c, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[fx, 0.0, c, 0.0, 0.0, fx, c, 0.0, 0.0, 0.0, 1.0, 0.0],
    )


def _pixel(tan_right: float, tan_forward: float) -> tuple[float, float]:
    c = IMAGE_SIZE_PX / 2
    return c + _FOCAL_PX * tan_right, c - _FOCAL_PX * tan_forward


def image_annotations(f: LiveFrame) -> Any:
    """The CNN's bearing (a cross, its pad probability beside it) and the estimator's pad
    seen from the vehicle (a circle of its 2-sigma horizontal uncertainty)."""
    from foxglove.messages import (
        CircleAnnotation,
        ImageAnnotations,
        Point2,
        PointsAnnotation,
        PointsAnnotationType,
        TextAnnotation,
    )

    when = frame_stamp(f)
    points, circles, texts = [], [], []
    if f.perception is not None:
        tan_r, tan_f, p = f.perception
        u, v = _pixel(tan_r, tan_f)
        seen = _color(0.1, 0.9, 0.1) if p >= 0.5 else _color(0.9, 0.6, 0.1)
        arm = 5.0
        points.append(
            PointsAnnotation(
                timestamp=when,
                type=PointsAnnotationType.LineList,
                points=[
                    Point2(x=u - arm, y=v),
                    Point2(x=u + arm, y=v),
                    Point2(x=u, y=v - arm),
                    Point2(x=u, y=v + arm),
                ],
                outline_color=seen,
                thickness=1.5,
            )
        )
        texts.append(
            TextAnnotation(
                timestamp=when,
                position=Point2(x=u + 6.0, y=v - 6.0),
                text=f"pad p={p:.2f}",
                font_size=9.0,
                text_color=seen,
                background_color=_color(0.0, 0.0, 0.0, 0.5),
            )
        )
    rel, quat = f.estimate_rel_ned_m, f.quat_wxyz
    if rel is not None and quat is not None:
        pixel = _project(-np.asarray(rel, float), np.asarray(quat, float))
        if pixel is not None:
            u, v, depth = pixel
            sigma = f.estimate_sigma_m
            radius = 3.0
            if sigma is not None and depth > 0.1:
                radius = max(radius, _FOCAL_PX * 2.0 * float(np.hypot(sigma[0], sigma[1])) / depth)
            circles.append(
                CircleAnnotation(
                    timestamp=when,
                    position=Point2(x=u, y=v),
                    diameter=2.0 * radius,
                    thickness=1.5,
                    outline_color=_color(0.2, 0.6, 1.0),
                    fill_color=_color(0.2, 0.6, 1.0, 0.15),
                )
            )
    return ImageAnnotations(circles=circles, points=points, texts=texts)


def _project(offset_ned: np.ndarray, quat_wxyz: np.ndarray) -> tuple[float, float, float] | None:
    """The pixel (u, v) and depth of a point ``offset_ned`` from the camera (None: behind)."""
    body = quat_to_rotation(quat_wxyz).T @ offset_ned  # FRD
    if body[2] <= 1e-3:
        return None
    c = IMAGE_SIZE_PX / 2
    return c + _FOCAL_PX * body[1] / body[2], c - _FOCAL_PX * body[0] / body[2], float(body[2])


def transforms(f: LiveFrame) -> Any:
    from foxglove.messages import FrameTransform, FrameTransforms

    when = frame_stamp(f)
    pos = f.vehicle_pos_ned_m if f.vehicle_pos_ned_m is not None else np.zeros(3)
    quat = f.quat_wxyz if f.quat_wxyz is not None else (1.0, 0.0, 0.0, 0.0)
    pad = f.pad_pos_ned_m if f.pad_pos_ned_m is not None else np.zeros(3)
    pad_q = f.pad_quat_wxyz if f.pad_quat_wxyz is not None else (1.0, 0.0, 0.0, 0.0)

    def tf(parent, child, translation, q_wxyz) -> Any:
        return FrameTransform(
            timestamp=when,
            parent_frame_id=parent,
            child_frame_id=child,
            translation=_vec(translation),
            rotation=_quat(q_wxyz),
        )

    x, y, z, w = _BODY_TO_OPTICAL_QUAT
    return FrameTransforms(
        transforms=[
            tf("ned", "vehicle", pos, quat),
            tf("ned", "vehicle_level", pos, (1.0, 0.0, 0.0, 0.0)),
            tf("ned", "pad", pad, pad_q),
            tf("vehicle", "camera", (0.0, 0.0, 0.0), (w, x, y, z)),
        ]
    )


def scene_update(f: LiveFrame, trail) -> Any:
    from foxglove.messages import (
        ArrowPrimitive,
        CubePrimitive,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
    )

    when = frame_stamp(f)

    def entity(frame_id: str, ident: str, **parts) -> Any:
        return SceneEntity(timestamp=when, frame_id=frame_id, id=ident, **parts)

    def lines(frame_id: str, ident: str, kind: Any, points: list, thickness: float, color: Any):
        """One entity of screen-space lines (``kind``: a strip or a list of segments)."""
        line = LinePrimitive(
            type=kind, pose=_pose(), thickness=thickness, scale_invariant=True, points=points,
            color=color,
        )  # fmt: skip
        return entity(frame_id, ident, lines=[line])

    length, width = f.pad_size_m
    entities = [
        entity(
            "ned",
            "ground",
            cubes=[
                CubePrimitive(
                    pose=_pose((0.0, 0.0, 0.02)),
                    size=_vec((200.0, 200.0, 0.02)),
                    color=_color(0.45, 0.42, 0.36, 0.6),
                )
            ],
        ),
        entity(
            "pad",
            "pad",
            cubes=[
                CubePrimitive(
                    pose=_pose((0.0, 0.0, -0.01)),
                    size=_vec((length, width, 0.02)),
                    color=_color(0.15, 0.6, 0.2),
                ),
                CubePrimitive(
                    pose=_pose((0.0, 0.0, -0.025)),
                    size=_vec((0.8 * length, 0.15 * width, 0.01)),
                    color=_color(0.8, 0.1, 0.1),
                ),
                CubePrimitive(
                    pose=_pose((0.0, 0.0, -0.025)),
                    size=_vec((0.15 * length, 0.8 * width, 0.01)),
                    color=_color(0.8, 0.1, 0.1),
                ),
            ],
        ),
        entity(
            "vehicle",
            "vehicle",
            cubes=[
                CubePrimitive(
                    pose=_pose(), size=_vec((0.7, 0.08, 0.05)), color=_color(0.2, 0.2, 0.25)
                ),
                CubePrimitive(
                    pose=_pose(), size=_vec((0.08, 0.7, 0.05)), color=_color(0.2, 0.2, 0.25)
                ),
                CubePrimitive(
                    pose=_pose((0.3, 0.0, 0.0)),
                    size=_vec((0.1, 0.1, 0.06)),
                    color=_color(0.9, 0.2, 0.2),
                ),
            ],
        ),
    ]
    if len(trail) >= 2:
        points = [Point3(x=p[0], y=p[1], z=p[2]) for p in trail]
        entities.append(
            lines(
                "ned",
                "trajectory",
                LinePrimitiveLineType.LineStrip,
                points,
                2.0,
                _color(0.2, 0.5, 1.0),
            )
        )
    depth = f.range_m if f.range_m is not None and math.isfinite(f.range_m) else 10.0
    half = depth * math.tan(math.radians(CAMERA_FOV_DEG) / 2)
    corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
    rays = []
    for cx, cy in corners:
        rays += [Point3(x=0.0, y=0.0, z=0.0), Point3(x=cx, y=cy, z=depth)]
    for (ax, ay), (bx, by) in zip(corners, corners[1:] + corners[:1], strict=True):
        rays += [Point3(x=ax, y=ay, z=depth), Point3(x=bx, y=by, z=depth)]
    entities.append(
        lines(
            "camera",
            "frustum",
            LinePrimitiveLineType.LineList,
            rays,
            1.0,
            _color(1.0, 1.0, 0.3, 0.8),
        )
    )
    if f.estimate_rel_ned_m is not None and f.vehicle_pos_ned_m is not None:
        pad_est = np.asarray(f.vehicle_pos_ned_m, float) - np.asarray(f.estimate_rel_ned_m, float)
        sigma = f.estimate_sigma_m if f.estimate_sigma_m is not None else np.full(3, 0.1)
        size = np.maximum(4.0 * np.asarray(sigma, float), 0.05)  # 2-sigma each way
        entities.append(
            entity(
                "ned",
                "estimated_pad",
                spheres=[
                    SpherePrimitive(
                        pose=_pose(pad_est), size=_vec(size), color=_color(0.2, 0.6, 1.0, 0.35)
                    )
                ],
            )
        )
    wind = f.wind_ned_m_s
    if wind is not None and float(np.linalg.norm(wind)) > 0.05:
        w = np.asarray(wind, float)
        speed = float(np.linalg.norm(w))
        yaw = math.atan2(w[1], w[0])
        pitch = -math.asin(max(-1.0, min(1.0, w[2] / speed)))
        q = (
            math.cos(yaw / 2) * math.cos(pitch / 2),
            -math.sin(yaw / 2) * math.sin(pitch / 2),
            math.cos(yaw / 2) * math.sin(pitch / 2),
            math.sin(yaw / 2) * math.cos(pitch / 2),
        )
        entities.append(
            entity(
                "vehicle_level",
                "wind",
                arrows=[
                    ArrowPrimitive(
                        pose=_pose((0.0, 0.0, -1.0), q),
                        shaft_length=speed * 0.3,
                        shaft_diameter=0.08,
                        head_length=0.3,
                        head_diameter=0.2,
                        color=_color(0.6, 0.9, 1.0),
                    )
                ],
            )
        )
    return SceneUpdate(entities=entities)


def state_values(f: LiveFrame) -> dict[str, Any]:
    out: dict[str, Any] = {"time_s": f.time_s}
    if f.command is not None:
        out["command"] = dict(
            zip(("thrust_norm", "p", "q", "r"), (float(v) for v in f.command), strict=True)
        )
    if f.quat_wxyz is not None:
        w, x, y, z = (float(v) for v in f.quat_wxyz)
        roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        out["attitude_deg"] = {
            "roll": math.degrees(roll),
            "pitch": math.degrees(pitch),
            "yaw": math.degrees(yaw),
        }
    if f.range_m is not None:
        out["range_m"] = _float(f.range_m)
    for key, value in (("estimate", f.estimate_rel_ned_m), ("truth", f.truth_rel_ned_m)):
        if value is not None:
            out[key] = dict(zip(("n", "e", "d"), (float(v) for v in value), strict=True))
    if f.perception is not None:
        out["pad_probability"] = float(f.perception[2])
    if f.state is not None:
        out["state"] = f.state
    if f.link:
        out["link"] = dict(f.link)
    return out
