"""``visland log plot`` and the demo's picture: one flight's four panels, or several flights
overlaid around the pad.

Each panel draws from the source :func:`tools.logtool.plot_sources` picks (ground truth before
measurements, the pilot's command before the autopilot's) and names it in its title; a panel
with no source is left out and the figure's footnote says what was missing. Time axes name
their clock (sim time for the SITL and rollouts, the companion's wall clock); clustered event
labels share one. matplotlib runs headless (Agg).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.contract.companion_records import CompanionSummaryRecord
from companion.contract.records import (
    TIME_S,
    EpisodeResultRecord,
    EventKind,
    EventRecord,
    RecordError,
)
from companion.contract.topics import TOPIC_EVENTS, TOPIC_GROUNDTRUTH
from companion.flightlog import FlightLog, read_log
from sitl_sim.metrics import SUCCESS_MAX_ERROR_M
from sitl_sim.physics.dynamics import quat_to_rotation
from tools.logtool import (
    PANEL_WIDTH,
    RESULT_TOPICS,
    SOURCES,
    PlotSources,
    fmt_value,
    last_result,
    log_kind,
    plot_sources,
    result_record,
    verdict,
)
from training.report.figures import draw_pad

__all__ = [
    "FlightsPlotReport",
    "PlotReport",
    "default_plot_path",
    "plot_flight",
    "plot_flights",
    "plot_log",
    "time_axis_label",
]

_MARKED_EVENTS = (
    EventKind.FLIGHT,
    EventKind.MODE,
    EventKind.FAILSAFE,
    EventKind.DISARMED,
    EventKind.FLIGHT_START,
    EventKind.STATE,
)
"""Event kinds drawn as vertical lines on the time plots (the SITL autopilot's mode/arming
story; the companion's state machine)."""


# --------------------------------------------------------------------------- series


def _array(msgs: list[dict[str, Any]], get: Callable[[dict[str, Any]], Any], width: int):
    """``(times (N,), values (N, width))`` with null/missing values as NaN."""
    times = np.array([float(m["time_s"]) for m in msgs], dtype=float)
    values = np.full((len(msgs), width), np.nan)
    for i, m in enumerate(msgs):
        try:
            v = get(m)
        except (KeyError, TypeError, IndexError):
            continue
        if v is None:
            continue
        row = np.asarray(v, dtype=float).reshape(-1)
        if row.size == width:
            values[i] = row
    return times, values


def _series(log: FlightLog, panel: str, topic: str) -> tuple[np.ndarray, np.ndarray, str]:
    """``(times (N,), values (N, width), label)`` of ``topic`` as :data:`SOURCES` reads it."""
    get, label = next((g, lab) for t, g, lab in SOURCES[panel] if t == topic)
    times, values = _array(log.topic(topic), get, PANEL_WIDTH[panel])
    return times, values, label


def _events(log: FlightLog) -> list[tuple[float, str]]:
    return [
        (float(m[TIME_S]), ev.text)
        for m, ev in _event_records(log)
        if ev.kind in _MARKED_EVENTS and TIME_S in m
    ]


def _event_records(log: FlightLog) -> list[tuple[dict[str, Any], EventRecord]]:
    """``(message, record)`` of every readable ``/events`` message."""
    out = []
    for m in log.topic(TOPIC_EVENTS):
        try:
            out.append((m, EventRecord.from_dict(m)))
        except RecordError:
            continue  # not an event this reader knows how to draw
    return out


# --------------------------------------------------------------------------- plot


def default_plot_path(path: str | Path) -> Path:
    """``<dir>/<name without .mcap/.part>.png``."""
    path = Path(path)
    name = path.name
    for suffix in (".part", ".mcap"):
        name = name.removesuffix(suffix)
    return path.with_name(name + ".png")


_LABEL_GAP = 0.04
"""Events closer than this share of the time axis share one label (the arming, mode and state
changes of a flight's first second would otherwise print over each other)."""


def _label_groups(events: list[tuple[float, str]], span_s: float) -> list[tuple[float, str]]:
    """One ``(time, label)`` per cluster of events: the first's text, ``(+N)`` for the rest."""
    groups: list[list[tuple[float, str]]] = []
    for t, text in sorted(events, key=lambda e: e[0]):
        if groups and t - groups[-1][0][0] < _LABEL_GAP * span_s:
            groups[-1].append((t, text))
        else:
            groups.append([(t, text)])
    return [(g[0][0], g[0][1] if len(g) == 1 else f"{g[0][1]} (+{len(g) - 1})") for g in groups]


def _mark_events(ax, events: list[tuple[float, str]], label: bool = False) -> None:
    for t, _ in events:
        ax.axvline(t, color="0.6", linestyle=":", linewidth=0.8)
    if not label or not events:
        return
    lo, hi = ax.get_xlim()
    for t, text in _label_groups(events, max(hi - lo, 1e-9)):
        ax.text(
            t,
            0.98,
            f" {text[:48]}",
            transform=ax.get_xaxis_transform(),
            rotation=90,
            va="top",
            fontsize=6,
            color="0.4",
        )


def time_axis_label(kind: str) -> str:
    """Which clock a log's ``time_s`` is on: the SITL and rollouts stamp sim time; the
    companion its own monotonic (wall) clock since the log was opened."""
    if kind == "companion":
        return "wall time since log start (s, companion clock)"
    if kind in ("sitl", "rollout"):
        return "sim time (s)"
    return "time_s (s)"


def _title(log: FlightLog, kind: str) -> str:
    head = f"{log.path.name} — {kind} log"
    if log.truncated:
        head += " (TRUNCATED: readable prefix only)"
    r = result_record(last_result(log))
    if r is None:
        return head + "\nno episode result"
    if isinstance(r, CompanionSummaryRecord):  # the companion's own account
        return f"{head}\ncompanion: {r.result} ({r.reason or 'no reason given'})"
    speed = r.touchdown_vertical_speed_m_s
    return (
        f"{head}\n{verdict(r)}: landing error {fmt_value(r.landing_error_m)} m, "
        f"vertical speed {fmt_value(speed)} m/s, tilt {fmt_value(r.tilt_deg)} deg"
    )


@dataclass(frozen=True)
class PlotReport:
    """What :func:`plot_flight` drew.

    Attributes:
        out: the PNG written.
        kind: sitl | rollout | companion | unknown.
        sources: panel -> topic drawn (None: panel left empty, see ``missing``).
        missing: one line per empty panel, naming the topics it looked for.
        truncated: the log was cut (crash); the plot shows its readable prefix.
        error: why reading stopped early, if it did.
        drawn: the panels drawn, in order (a panel without data is left out).
        clock: the time axes' label (which clock ``time_s`` is on).
    """

    out: Path
    kind: str
    sources: dict[str, str | None]
    missing: list[str]
    truncated: bool
    error: str | None
    drawn: tuple[str, ...] = ()
    clock: str = ""


def plot_log(path: str | Path, out: str | Path | None = None) -> Path:
    """Draw one flight log to a PNG and return its path (see :func:`plot_flight`)."""
    return plot_flight(path, out).out


def plot_flight(path: str | Path, out: str | Path | None = None) -> PlotReport:
    """Draw one flight log to a PNG (default :func:`default_plot_path`) and say what it drew.

    Panels: top view (north/east) around the pad; altitude vs time; roll/pitch/yaw vs time;
    thrust_norm and body-rate commands vs time. A panel without data says which topics it
    looked for (see :func:`plot_sources`).

    Raises:
        FlightLogError: the file is missing or not an MCAP file.
    """
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window (CI, SSH, a companion computer)
    import matplotlib.pyplot as plt

    wanted = {t for rows in SOURCES.values() for t, _, _ in rows}
    wanted |= {*RESULT_TOPICS, TOPIC_EVENTS}
    log = read_log(path, topics=wanted)
    kind = log_kind(set(log.schemas))  # every channel, read or not
    src = plot_sources(log)
    events = _events(log)
    out_path = Path(out) if out is not None else default_plot_path(path)

    clock = time_axis_label(kind)
    panels = [
        (panel, draw, title, xlabel, ylabel)
        for panel, draw, title, xlabel, ylabel in (
            ("position", _draw_top, "top view", "east (m)", "north (m)"),
            ("altitude", _draw_altitude, "altitude", clock, "m"),
            ("attitude", _draw_attitude, "attitude", clock, "deg"),
            ("command", _draw_commands, "commands", clock, None),
        )
        if src.sources[panel] is not None  # a panel without data is left out, not drawn empty
    ]
    if _pad_track(log) is not None:  # a moving or tilted pad: the path as seen from it too
        panels.insert(
            1, ("pad frame", _draw_pad_frame, "in the pad's frame", "right (m)", "forward (m)")
        )
    rows, cols = (1, max(1, len(panels))) if len(panels) <= 2 else (2, (len(panels) + 1) // 2)
    fig, axes = plt.subplots(rows, cols, figsize=(6.5 * cols, 4.5 * rows + 0.5), squeeze=False)
    try:
        flat = list(axes.flat)
        for ax, (panel, draw, title, xlabel, ylabel) in zip(flat, panels, strict=False):
            topic = src.sources.get(panel, TOPIC_GROUNDTRUTH)
            draw(ax, log, topic, events)
            ax.set_title(f"{title} ({topic})", fontsize=10)
            ax.set_xlabel(xlabel)
            if ylabel is not None:
                ax.set_ylabel(ylabel)
        for ax in flat[len(panels) :]:
            ax.remove()
        if not panels:
            fig.text(0.5, 0.5, "nothing to plot", ha="center", va="center")
        if src.missing:  # what was looked for and not found, said once below the panels
            fig.text(
                0.01, 0.005, "not in this log: " + "; ".join(src.missing), fontsize=7, va="bottom"
            )

        fig.suptitle(_title(log, kind), fontsize=11)
        fig.tight_layout(rect=(0, 0.02, 1, 1))
        out_path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out_path, dpi=100)
    finally:
        plt.close(fig)
    drawn = tuple(panel for panel, *_ in panels)
    return PlotReport(
        out_path, kind, src.sources, src.missing, log.truncated, log.error, drawn, clock
    )


def _draw_top(ax, log: FlightLog, topic: str, events: list[tuple[float, str]]) -> None:
    """Top view: east to the right, north up, the pad and its cross at the origin (no event
    marks: a map has no time axis)."""
    _, pos, _ = _series(log, "position", topic)
    draw_pad(ax, success_circle=False)
    ax.plot(pos[:, 1], pos[:, 0], color="tab:blue", linewidth=1.2, label="path")
    ax.plot(pos[0, 1], pos[0, 0], "o", color="tab:blue", label="start")
    ax.plot(pos[-1, 1], pos[-1, 0], "x", color="k", markersize=9, label="end")
    reach = pos[:, :2]
    track = _pad_track(log)
    if track is not None:  # a pad that moves: its path in the world too
        pad = track[1]
        ax.plot(
            pad[:, 1], pad[:, 0], "--", color="tab:orange", linewidth=2.0, label="pad", zorder=1
        )
        ax.plot(pad[-1, 1], pad[-1, 0], "s", color="tab:orange", markersize=6)
        reach = np.vstack([reach, pad[:, :2]])
    span = max(3.0, float(np.nanmax(np.abs(reach))) * 1.15)
    ax.set_xlim(-span, span)
    ax.set_ylim(-span, span)
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)


def _pad_track(log: FlightLog) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(vehicle NED (n, 3), pad NED (n, 3), pad attitude quaternions (n, 4)) from the ground
    truth of a flight on a site (None: the still pad at the origin, or no ground truth)."""
    msgs = [m for m in log.topic(TOPIC_GROUNDTRUTH) if "pad_pos_ned_m" in m]
    if not msgs:
        return None
    return tuple(  # type: ignore[return-value]
        np.array([m[k] for m in msgs], dtype=float)
        for k in ("pos_ned_m", "pad_pos_ned_m", "pad_quat_wxyz")
    )


def _draw_pad_frame(ax, log: FlightLog, topic: str, events: list[tuple[float, str]]) -> None:
    """The vehicle's path relative to the pad, in the pad's frame (right across, forward up):
    what landing on a moving pad is."""
    pos, pad, quat = _pad_track(log) or (np.zeros((0, 3)),) * 3
    rel = np.array(
        [quat_to_rotation(q).T @ (p - c) for p, c, q in zip(pos, pad, quat, strict=True)]
    )
    draw_pad(ax, success_circle=True)
    ax.plot(rel[:, 1], rel[:, 0], color="tab:purple", linewidth=1.2, label="path from the pad")
    ax.plot(rel[-1, 1], rel[-1, 0], "x", color="k", markersize=9, label="end")
    span = max(3.0, float(np.nanmax(np.abs(rel[:, :2]))) * 1.15)
    ax.set_xlim(-span, span)
    ax.set_ylim(-span, span)
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)


def _draw_altitude(ax, log: FlightLog, topic: str, events: list[tuple[float, str]]) -> None:
    """Altitude (or range) against time, the radar's measurement beside the truth."""
    t, alt, label = _series(log, "altitude", topic)
    ax.plot(t, alt[:, 0], color="tab:blue", label=label)
    radar = next(
        (t for t, _, lab in SOURCES["altitude"] if lab.startswith("radar") and log.topic(t)),
        None,
    )
    if radar is not None and radar != topic:
        t2, rng, label2 = _series(log, "altitude", radar)
        ax.plot(t2, rng[:, 0], color="tab:orange", linewidth=0.8, label=label2)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    _mark_events(ax, events, label=True)


def _draw_attitude(ax, log: FlightLog, topic: str, events: list[tuple[float, str]]) -> None:
    """Roll, pitch and yaw (degrees) against time."""
    t, att, _ = _series(log, "attitude", topic)
    for k, name in enumerate(("roll", "pitch", "yaw")):
        ax.plot(t, np.degrees(att[:, k]), label=name)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    _mark_events(ax, events)


def _draw_commands(ax, log: FlightLog, topic: str, events: list[tuple[float, str]]) -> None:
    """thrust_norm (left axis) and the body-rate commands (right axis) as steps in time."""
    t, cmd, label = _series(log, "command", topic)
    thrust, rates = cmd[:, 0], cmd[:, 1:]
    ax.step(t, thrust, where="post", color="k", label=f"thrust_norm ({label})")
    ax.set_ylabel("thrust_norm")
    ax.set_ylim(-0.02, 1.02)
    ax_rate = ax.twinx()
    for k, name in enumerate(("p (roll rate)", "q (pitch rate)", "r (yaw rate)")):
        ax_rate.step(t, rates[:, k], where="post", linewidth=0.9, label=name)
    ax_rate.set_ylabel("body rate (rad/s, FRD)")
    handles = ax.get_legend_handles_labels()
    rate_handles = ax_rate.get_legend_handles_labels()
    ax.legend(handles[0] + rate_handles[0], handles[1] + rate_handles[1], fontsize=8)
    ax.grid(alpha=0.3)
    _mark_events(ax, events)


def _missing_line(src: PlotSources, panel: str) -> str:
    line = next(m for m in src.missing if m.startswith(panel + ":"))
    return line.split(": ", 1)[1]


# --------------------------------------------------------------------------- several flights

_FLIGHT_START_EVENTS = (EventKind.FLIGHT, EventKind.FLIGHT_START)
"""Event kinds that mark the start of the flight proper (SITL: OFFBOARD/LAND took over;
companion: the policy took over); the multi-flight plot's clock starts there."""
_ZOOM_HALF_M = 3.0  # the touchdown panel: the pad (+-2 m) and a margin


@dataclass(frozen=True)
class FlightsPlotReport:
    """What :func:`plot_flights` drew.

    Attributes:
        out: the PNG written.
        drawn: the logs drawn (those with a position source), in the order given.
        skipped: ``"<path>: why"`` for each log left out of the picture.
        outside_zoom: logs whose touchdown point lies outside the touchdown panel.
    """

    out: Path
    drawn: list[Path]
    skipped: list[str]
    outside_zoom: list[Path]


def _flight_start_s(log: FlightLog, first_sample_s: float) -> float:
    starts = [
        float(m[TIME_S])
        for m, ev in _event_records(log)
        if ev.kind in _FLIGHT_START_EVENTS and TIME_S in m
    ]
    return min(starts) if starts else first_sample_s


def _flight_label(path: Path, log: FlightLog, label: str | None) -> str:
    r = result_record(last_result(log))
    head = label if label is not None else path.name.removesuffix(".mcap")
    if not isinstance(r, EpisodeResultRecord):
        return f"{head}: no episode result"
    return f"{head}: {verdict(r)}, error {fmt_value(r.landing_error_m)} m"


def plot_flights(
    paths: list[str | Path],
    out: str | Path,
    title: str | None = None,
    labels: list[str] | None = None,
) -> FlightsPlotReport:
    """Draw several flights of one run overlaid in one PNG and say what it drew.

    Panels: top view (north/east) of every path around the pad; the touchdown area (the pad,
    the 1 m success circle, each flight's end point); altitude vs time since each flight's
    start (the ``flight``/``flight_start`` event: the HOLD before it is left out). Each flight
    keeps one colour, its legend entry gives its result (:func:`verdict`) and landing error.
    Position and altitude take the best source the log has (:data:`SOURCES`); a log with no
    position source is skipped and named in the report.

    Args:
        paths: flight logs (SITL or rollout logs carry ground truth; a vision companion's
            log has none and is skipped).
        out: the PNG to write (its folder is created).
        title: the figure title (default: how many flights succeeded).
        labels: one legend name per path (default: the file name).

    Raises:
        ValueError: no paths, or ``labels`` of another length.
        FlightLogError: a file is missing or not an MCAP file.
    """
    if not paths:
        raise ValueError("plot_flights: no flight logs given")
    if labels is not None and len(labels) != len(paths):
        raise ValueError(f"plot_flights: {len(labels)} labels for {len(paths)} logs")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    wanted = {t for panel in ("position", "altitude") for t, _, _ in SOURCES[panel]}
    wanted |= {*RESULT_TOPICS, TOPIC_EVENTS}
    out_path = Path(out)
    drawn: list[Path] = []
    skipped: list[str] = []
    outside: list[Path] = []
    successes = 0
    fig, (ax_top, ax_zoom, ax_alt) = plt.subplots(
        1, 3, figsize=(18, 6.2), gridspec_kw={"width_ratios": [1, 1, 1.35]}
    )
    try:
        draw_pad(ax_top, success_circle=False)
        draw_pad(ax_zoom, success_circle=False)
        ax_zoom.add_patch(
            Circle((0, 0), SUCCESS_MAX_ERROR_M, fill=False, linestyle="--", color="k", lw=1)
        )
        span = 3.0
        colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
        for k, path in enumerate(Path(p) for p in paths):
            log = read_log(path, topics=wanted)
            src = plot_sources(log)
            if src.sources["position"] is None:
                skipped.append(f"{path}: {_missing_line(src, 'position')}")
                continue
            colour = colours[len(drawn) % len(colours)]
            label = _flight_label(path, log, labels[k] if labels is not None else None)
            r = result_record(last_result(log))
            successes += isinstance(r, EpisodeResultRecord) and r.success
            t, pos, _ = _series(log, "position", src.sources["position"])
            t0 = _flight_start_s(log, float(t[0]))
            keep = t >= t0 - 1e-9
            if keep.any():
                t, pos = t[keep], pos[keep]
            ax_top.plot(pos[:, 1], pos[:, 0], color=colour, linewidth=1.3, label=label)
            ax_top.plot(pos[0, 1], pos[0, 0], "o", color=colour)
            ax_top.plot(pos[-1, 1], pos[-1, 0], "x", color=colour, markersize=9)
            span = max(span, float(np.nanmax(np.abs(pos[:, :2]))) * 1.1)
            ax_zoom.plot(pos[:, 1], pos[:, 0], color=colour, linewidth=1.0, alpha=0.6)
            ax_zoom.plot(pos[-1, 1], pos[-1, 0], "x", color=colour, markersize=11, mew=2.5)
            if np.nanmax(np.abs(pos[-1, :2])) > _ZOOM_HALF_M:
                outside.append(path)
            alt_topic = src.sources["altitude"]
            if alt_topic is not None:
                ta, alt, _ = _series(log, "altitude", alt_topic)
                sel = ta >= t0 - 1e-9
                ax_alt.plot(ta[sel] - t0, alt[sel, 0], color=colour, label=label)
            drawn.append(path)

        ax_top.set_xlim(-span, span)
        ax_top.set_ylim(-span, span)
        ax_top.set_aspect("equal")
        ax_top.set_title("top view: o start, x touchdown (ground truth)", fontsize=10)
        ax_top.set_xlabel("east (m)")
        ax_top.set_ylabel("north (m)")
        ax_top.grid(alpha=0.3)
        ax_top.legend(loc="upper left", fontsize=8)

        ax_zoom.set_xlim(-_ZOOM_HALF_M, _ZOOM_HALF_M)
        ax_zoom.set_ylim(-_ZOOM_HALF_M, _ZOOM_HALF_M)
        ax_zoom.set_aspect("equal")
        zoom_title = "touchdown: pad (4 m), dashed = 1 m success radius"
        if outside:
            zoom_title += f"\n{len(outside)} touchdown(s) outside this view"
        ax_zoom.set_title(zoom_title, fontsize=10)
        ax_zoom.set_xlabel("east (m)")
        ax_zoom.set_ylabel("north (m)")
        ax_zoom.grid(alpha=0.3)

        ax_alt.set_title("altitude since the flight started", fontsize=10)
        ax_alt.set_xlabel("sim time since flight start (s)")
        ax_alt.set_ylabel("altitude above ground (m)")
        ax_alt.grid(alpha=0.3)
        if ax_alt.get_legend_handles_labels()[0]:
            ax_alt.legend(fontsize=8)

        default = f"{len(drawn)} flights: {successes} successful landings"
        fig.suptitle(title if title is not None else default, fontsize=12)
        fig.tight_layout()
        out_path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out_path, dpi=100)
    finally:
        plt.close(fig)
    return FlightsPlotReport(out_path, drawn, skipped, outside)
