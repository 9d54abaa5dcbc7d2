"""The ``[pad]`` scenario section: which pad is landed on, and how it moves.

``design``  a pad file (``configs/pads/NAME.toml``, :mod:`sitl_sim.render.pads`) or a list of
            them, one drawn per episode; a path is relative to the scenario file (else to the
            repository root), a bare name is a shipped pad (``"helipad_1m"``). Default: the
            paper's 4 m pad.
``motion``  ``"static"`` (default), ``"rover"`` (the pad on a rover's roof, driving curves) or
            ``"deck"`` (the pad on a ship's deck at sea: heave, roll, pitch, a slow drift); the
            models: :mod:`sitl_sim.site.pad_motion`, the vehicles: :mod:`sitl_sim.site.vehicle`
``height_m``          the pad's surface above the ground or the water (a roof, a deck, a
                      platform under a still pad)
``speed_m_s``, ``heading_deg``  the rover's speed and start heading; the deck's drift
``turn_rate_deg_s``   the band the rover's turn rate wanders in (``[r, r]``: a circle, ``[0, 0]``:
                      straight)
``heave_m``, ``roll_deg``, ``pitch_deg``  the deck's amplitudes (peaks of a sum of three
                      sinusoids with random phases); ``heave_period_s`` their main period

Every span is drawn per episode; a rover's or deck's key on another motion is a ConfigError.
The pad is drawn at its true size by both renderers; ``[visual] pad_scale`` and
``pad_colour_jitter`` apply to any design. Absent section (or the paper's pad, still, at height
0): the nominal pad and site, bit for bit. The design comes from its own generator ``(seed,
episode, PAD_STREAM)``, the motion from ``(seed, episode, PAD_MOTION_STREAM)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from companion.table import Section, amount, choice, file_list, span
from sitl_sim.errors import ConfigError
from sitl_sim.render.pads import PadDesign, builtin_pad_paths, find_file, load_pad
from sitl_sim.site.pad_motion import Ground, PadMotion, draw_pad_motion

__all__ = ["MOTIONS", "PAD_MOTION_STREAM", "PAD_STREAM", "PadConfig"]

PAD_STREAM = 0x5041_4421  # "PAD!"
PAD_MOTION_STREAM = 0x5041_444D  # "PADM"
MOTIONS = ("static", "rover", "deck")
_ROVER_KEYS = ("turn_rate_deg_s",)
_DECK_KEYS = ("heave_m", "roll_deg", "pitch_deg")


@dataclass(frozen=True)
class PadConfig(Section):
    """The checked ``[pad]`` section (the pad files are read and checked when it is built)."""

    SECTION: ClassVar[str] = "pad"

    design: tuple[str, ...] | None = file_list(
        doc="pad file(s) configs/pads/NAME.toml (or a shipped pad's NAME), one drawn per "
        "episode; relative to the scenario file (absent: the paper's 4 m pad)"
    )
    motion: str = choice(
        "static", MOTIONS, doc="still, on a rover's roof, or on a ship's deck at sea"
    )
    height_m: tuple[float, float] = amount(
        unit="m", hi=10.0, doc="the pad's surface above the ground or water"
    )
    speed_m_s: tuple[float, float] = amount(
        unit="m/s", hi=20.0, doc="rover: speed; deck: drift speed"
    )
    heading_deg: tuple[float, float] = span(
        (0.0, 360.0),
        unit="deg",
        lo=-360.0,
        hi=720.0,
        doc="rover: start heading; deck: heading and drift direction (from north, clockwise)",
    )
    turn_rate_deg_s: tuple[float, float] = span(
        (0.0, 0.0),
        unit="deg/s",
        lo=-90.0,
        hi=90.0,
        doc="rover: the band its turn rate wanders "
        "in (two slow sinusoids); [r, r] a circle, [0, 0] straight",
    )
    heave_m: tuple[float, float] = amount(unit="m", hi=5.0, doc="deck: heave amplitude (peak)")
    heave_period_s: tuple[float, float] = span(
        (6.0, 10.0),
        unit="s",
        lo=1.0,
        hi=60.0,
        doc="deck: main period of the heave (roll and "
        "pitch: 1.15 and 0.9 x it), with two more lines at 0.55-0.8 and 1.2-1.6 x",
    )
    roll_deg: tuple[float, float] = amount(unit="deg", hi=30.0, doc="deck: roll amplitude (peak)")
    pitch_deg: tuple[float, float] = amount(unit="deg", hi=30.0, doc="deck: pitch amplitude (peak)")
    designs: tuple[PadDesign, ...] = field(default=(), init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        self._check_motion_keys()
        where = f"{self.source}: [pad] design"
        shipped = builtin_pad_paths()
        loaded = []
        for name in self.design or ():
            path = shipped[name] if name in shipped else find_file(name, self.source, where)
            loaded.append(load_pad(path))
        object.__setattr__(self, "designs", tuple(loaded))

    def _check_motion_keys(self) -> None:
        """A rover's or a deck's key set on another motion is refused, not ignored."""
        own = {"static": (), "rover": _ROVER_KEYS, "deck": _DECK_KEYS}[self.motion]
        moving = ("speed_m_s",) if self.motion == "static" else ()
        for key in (*_ROVER_KEYS, *_DECK_KEYS, *moving):
            if key not in own and getattr(self, key) != (0.0, 0.0):
                value = getattr(self, key)
                wants = (
                    "rover"
                    if key in _ROVER_KEYS
                    else "deck"
                    if key in _DECK_KEYS
                    else ("rover or deck")
                )
                raise ConfigError(
                    f"{self.source}: [pad] {key} = [{value[0]}, {value[1]}] with motion = "
                    f"{self.motion!r}; expected motion = {wants!r} for it (or leave it out)"
                )

    @property
    def still_on_ground(self) -> bool:
        """The nominal site: a still pad at height 0 (the motion draws nothing)."""
        return self.motion == "static" and self.height_m == (0.0, 0.0)

    def draw_motion(
        self,
        seed: int,
        index: int,
        ground: Ground | None = None,
        ground_gradient: tuple[float, float] = (0.0, 0.0),
    ) -> PadMotion:
        """Episode ``index`` of ``seed``'s pad motion, on ``ground`` (the terrain's height and
        gradient under a rover; None: flat) with ``ground_gradient`` under a still pad."""
        rng = np.random.default_rng([int(seed), int(index), PAD_MOTION_STREAM])
        return draw_pad_motion(rng, self, ground, ground_gradient)

    def draw(self, seed: int, index: int) -> PadDesign | None:
        """Episode ``index`` of ``seed``'s pad (None: the nominal pad)."""
        if not self.designs:
            return None
        rng = np.random.default_rng([int(seed), int(index), PAD_STREAM])
        return self.designs[int(rng.integers(len(self.designs)))]
