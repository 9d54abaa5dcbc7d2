"""A scripted pymavlink client of ``visland sitl``: what a companion does, minus the policy.

Used by the SITL's flight-card tests and by ``bench_sitl``. It speaks MAVLink 2 through the
``pymavlink.dialects.v20.common`` codec directly (no ``mavutil``, so no MAVLINK20 trap), binds
the offboard API port the SITL sends to, and reads camera frames from the camera port.
"""

from __future__ import annotations

import select
import socket
import time
from collections import Counter, deque
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.contract import Command
from companion.contract.camera_packet import CameraFrame, CameraPacketError, FrameAssembler
from companion.contract.signing import sign_outgoing
from companion.telemetry import OdometrySample, odometry_from_msg

__all__ = [
    "OFFBOARD_CUSTOM_MODE",
    "ClientTimeout",
    "SitlClient",
]

OFFBOARD_CUSTOM_MODE = 6 << 16
LAND_CUSTOM_MODE = (4 << 16) | (6 << 24)
HOLD_CUSTOM_MODE = (4 << 16) | (3 << 24)


class ClientTimeout(TimeoutError):
    """A wait of the scripted client ran out (names what it waited for)."""


class SitlClient(AbstractContextManager):
    """Offboard-API side of the link.

    Args:
        sitl_addr: (host, port) the SITL is bound to (its 14580).
        local_port: port to bind, the SITL's remote port (its 14540).
        camera_port: port to bind for camera frames (None: no camera socket).
        sysid / compid: our ids (255/190: a ground-station-like offboard client).
        signing_key: 32-byte key to sign everything we send (None: unsigned).
    """

    def __init__(
        self,
        sitl_addr: tuple[str, int],
        local_port: int,
        camera_port: int | None = None,
        *,
        host: str = "127.0.0.1",
        sysid: int = 255,
        compid: int = 190,
        signing_key: bytes | None = None,
    ) -> None:
        self.sitl_addr = sitl_addr
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 * 1024 * 1024)
        self.sock.bind((host, local_port))
        self.sock.setblocking(False)
        self.cam: socket.socket | None = None
        if camera_port is not None:
            self.cam = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.cam.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 * 1024 * 1024)
            self.cam.bind((host, camera_port))
            self.cam.setblocking(False)
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if signing_key is not None:
            sign_outgoing(self.mav, signing_key, link_id=1)
        self.last: dict[str, Any] = {}
        self.counts: Counter[str] = Counter()
        self.inbox: deque[Any] = deque(maxlen=100_000)
        self.statustexts: list[str] = []
        self._assembler = FrameAssembler()
        self.frames_received = 0
        self.bad_frames = 0

    def close(self) -> None:
        self.sock.close()
        if self.cam is not None:
            self.cam.close()

    def __exit__(self, *exc: object) -> None:  # ``with SitlClient(...) as c``: c is self
        self.close()

    # ------------------------------------------------------------------ MAVLink

    def send(self, msg: Any) -> None:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self.sock.sendto(buf, self.sitl_addr)

    def poll(self, timeout_s: float = 0.0) -> int:
        """Receive what is waiting (after up to ``timeout_s`` for the first datagram)."""
        if timeout_s > 0:
            select.select([self.sock], [], [], timeout_s)
        n = 0
        while True:
            try:
                data, _ = self.sock.recvfrom(65_535)
            except BlockingIOError:
                return n
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = True
            for msg in parser.parse_buffer(data) or []:
                name = msg.get_type()
                self.last[name] = msg
                self.counts[name] += 1
                self.inbox.append(msg)
                if name == "STATUSTEXT":
                    self.statustexts.append(msg.text)
                n += 1

    def wait_for(
        self,
        name: str,
        timeout_s: float = 5.0,
        predicate: Callable[[Any], bool] | None = None,
        *,
        fresh: bool = True,
    ) -> Any:
        """The next ``name`` message that satisfies ``predicate``: received from now on
        (``fresh``), or also among those already received and not yet consumed."""
        if fresh:
            self.inbox.clear()
        deadline = time.monotonic() + timeout_s
        while True:
            while self.inbox:
                msg = self.inbox.popleft()
                if msg.get_type() == name and (predicate is None or predicate(msg)):
                    return msg
            left = deadline - time.monotonic()
            if left <= 0:
                raise ClientTimeout(f"no {name} within {timeout_s} s")
            self.poll(min(left, 0.05))

    def command_long(
        self, command: int, *params: float, timeout_s: float = 3.0, target: tuple = (1, 1)
    ) -> int:
        """Send COMMAND_LONG and return the COMMAND_ACK result."""
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        self.inbox.clear()
        self.send(self.mav.command_long_encode(target[0], target[1], command, 0, *p))
        deadline = time.monotonic() + timeout_s
        while True:
            while self.inbox:
                msg = self.inbox.popleft()
                if msg.get_type() == "COMMAND_ACK" and msg.command == command:
                    return int(msg.result)
            left = deadline - time.monotonic()
            if left <= 0:
                raise ClientTimeout(f"no COMMAND_ACK for command {command} within {timeout_s} s")
            self.poll(min(left, 0.05))

    def set_offboard(self, timeout_s: float = 3.0) -> int:
        return self.command_long(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0, timeout_s=timeout_s)

    def setpoint(
        self,
        thrust_norm: float,
        rate_frd_rad_s=(0.0, 0.0, 0.0),
        time_boot_ms: int = 0,
        type_mask: int = 128,
        target: tuple[int, int] = (1, 1),
        q=(1.0, 0.0, 0.0, 0.0),
    ) -> None:
        """SET_ATTITUDE_TARGET (type_mask 128 = thrust + body rates, the Command contract)."""
        r = [float(v) for v in rate_frd_rad_s]
        self.send(
            self.mav.set_attitude_target_encode(
                time_boot_ms,
                target[0],
                target[1],
                type_mask,
                list(q),
                r[0],
                r[1],
                r[2],
                float(thrust_norm),
            )
        )

    def command(self, cmd: Command, time_boot_ms: int) -> None:
        self.setpoint(cmd.thrust_norm, cmd.rate_frd_rad_s, time_boot_ms)

    # ------------------------------------------------------------------ camera

    def next_frame(self, timeout_s: float = 5.0) -> CameraFrame:
        """The next complete camera frame (MAVLink is polled while waiting)."""
        if self.cam is None:
            raise ValueError("this client has no camera socket")
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                data, _ = self.cam.recvfrom(65_535)
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ClientTimeout(f"no camera frame within {timeout_s} s") from None
                select.select([self.cam, self.sock], [], [], min(left, 0.05))
                self.poll()
                continue
            try:
                frame = self._assembler.add(data)
            except CameraPacketError:
                self.bad_frames += 1
                continue
            if frame is not None:
                self.frames_received += 1
                return frame

    def truth_at(self, time_us: int, timeout_s: float = 1.0) -> OdometrySample:
        """The ODOMETRY (needs ``--groundtruth``) stamped at ``time_us`` or later, decoded as
        the companion decodes it (``companion.telemetry.odometry_from_msg``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            self.poll()
            msg = self.last.get("ODOMETRY")
            if msg is not None and msg.time_usec >= time_us:
                truth = odometry_from_msg(msg)
                if truth is None:
                    raise ValueError(f"ODOMETRY at {msg.time_usec} us is not usable: {msg}")
                return truth
            left = deadline - time.monotonic()
            if left <= 0:
                raise ClientTimeout(f"no ODOMETRY at or after {time_us} us")
            self.poll(min(left, 0.02))
