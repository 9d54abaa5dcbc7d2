"""The SITL's flight-log writes, queued and written while the loop would otherwise wait.

In lockstep the SITL sends a camera frame and then blocks until the companion answers it.
Encoding the control period's ~25 records (JSON, zstd, MCAP) on the spot put them on every
frame's critical path, although the loop then sat idle for as long as the companion computes.
:class:`LogQueue` opens the episode's :class:`~companion.flightlog.FlightLogWriter` and hands
:class:`~sitl_sim.mavlink.flight_log.FlightLog` a :class:`QueuedWriter` in its place: each write
is queued with its arguments (the sim-time stamp is one of them: nothing is read again later)
and run in order by :meth:`LogQueue.drain`, which the loop calls from the lockstep wait and the
paced sleeps, stopping as soon as a datagram is waiting. The queue is written at once when it
grows past ``max_pending`` (phases nobody waits in: LAND running free) and when the log closes.

The file holds the same records in the same order as when each was written on the spot; only
the wall time of the writes moves (and with it where the wall-clock chunk flushes fall, which
never were reproducible in a SITL log).

A write that fails (a full disk, a file-size limit, an I/O error) never stops the flight: the
episode's log is abandoned there (what reached the file reads back as a truncated log), its other
writes are dropped, and ``on_failure`` is told once (the SITL says it in a STATUSTEXT); the next
episode tries a new file.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.contract.perf import LoopPerf
from companion.flightlog import FlightLogError, FlightLogWriter

__all__ = ["LogQueue", "QueuedWriter"]


class LogQueue:
    """Flight-log writes waiting to be run (see the module docstring).

    Args:
        perf: where the writes' wall time is counted (part ``log``, inside whatever part
            drains the queue).
        max_pending: writes kept waiting at most; one more writes them all at once.
        on_failure: told ``"flight log stopped: <why> (<file>)"`` when an episode's log cannot
            be opened or written.
    """

    def __init__(
        self,
        perf: LoopPerf,
        max_pending: int = 1024,
        on_failure: Callable[[str], None] | None = None,
    ) -> None:
        if max_pending < 1:
            raise ValueError(f"max_pending = {max_pending}; expected >= 1")
        self._perf = perf
        self._max_pending = max_pending
        self.on_failure = on_failure
        self._pending: deque[tuple[Callable[..., Any], tuple[Any, ...]]] = deque()

    @property
    def pending(self) -> int:
        """Writes waiting."""
        return len(self._pending)

    def open_writer(self, path: Path, metadata: dict[str, Any]) -> QueuedWriter:
        """Open the episode's log file now (its metadata written) and return the writer that
        queues its records: the ``open_writer`` of
        :class:`~sitl_sim.mavlink.flight_log.FlightLog`."""
        try:
            return QueuedWriter(self, FlightLogWriter(path, metadata=metadata), Path(path))
        except (OSError, FlightLogError) as exc:  # cannot even start it: a failed log
            writer = QueuedWriter(self, None, Path(path))
            writer.fail(exc)
            return writer

    def put(self, write: Callable[..., Any], args: tuple[Any, ...]) -> None:
        """Queue ``write(*args)``; past ``max_pending`` run every waiting write now."""
        self._pending.append((write, args))
        if len(self._pending) > self._max_pending:
            self.drain()

    def drain(self, stop: Callable[[], bool] | None = None) -> None:
        """Run the waiting writes in order, until none is left or ``stop()`` says something
        more urgent arrived (checked before each write)."""
        pending, perf = self._pending, self._perf
        t = perf.now()
        try:
            while pending and (stop is None or not stop()):
                write, args = pending.popleft()
                write(*args)
        finally:
            perf.add_inner("log", t)


class QueuedWriter:
    """The episode's writer as :class:`~sitl_sim.mavlink.flight_log.FlightLog` sees it: the
    :class:`~companion.flightlog.FlightLogWriter` calls it makes, queued on ``queue``;
    :meth:`close` writes what is waiting and closes the file at once. After a failed write
    (:meth:`fail`) it writes nothing more."""

    def __init__(self, queue: LogQueue, writer: FlightLogWriter | None, path: Path) -> None:
        self._queue = queue
        self._writer = writer
        self.path = path
        self.failed: str | None = None
        """Why the log stopped (None: it did not)."""

    def fail(self, exc: BaseException) -> None:
        """Stop this log: keep what reached the file, drop the rest, tell ``on_failure``."""
        if self.failed is not None:
            return
        why = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
        self.failed = f"{why} ({self.path})"
        if self._writer is not None:
            self._writer.abandon()
        if self._queue.on_failure is not None:
            self._queue.on_failure(f"flight log stopped: {self.failed}")

    def _run(self, write: Callable[..., Any], args: tuple[Any, ...]) -> None:
        if self.failed is None:
            try:
                write(*args)
            except OSError as exc:
                self.fail(exc)

    def _put(self, name: str, args: tuple[Any, ...]) -> None:
        if self.failed is None:
            self._queue.put(self._run, (getattr(self._writer, name), args))

    def write(self, *args: Any) -> None:
        """:meth:`FlightLogWriter.write`, queued."""
        self._put("write", args)

    def write_mavlink(self, *args: Any) -> None:
        """:meth:`FlightLogWriter.write_mavlink`, queued (the message's fields are read when
        it runs)."""
        self._put("write_mavlink", args)

    def write_record(self, *args: Any) -> None:
        """``FlightLogWriter.write_record`` (a typed record), queued."""
        self._put("write_record", args)

    def write_image(self, *args: Any) -> None:
        """:meth:`FlightLogWriter.write_image`, queued."""
        self._put("write_image", args)

    def write_pose(self, *args: Any) -> None:
        """:meth:`FlightLogWriter.write_pose`, queued."""
        self._put("write_pose", args)

    def close(self) -> None:
        """Write every queued record (this log's and any before it), then close the file."""
        self._queue.drain()
        if self.failed is None and self._writer is not None:
            self._run(self._writer.close, ())
