"""The ``[pad]`` scenario section: which pad is landed on (its motion is a later section's keys).

``design``  a pad file (``configs/pads/NAME.toml``, :mod:`sitl_sim.render.pads`) or a list of
            them, one drawn per episode; a path is relative to the scenario file (else to the
            repository root), a bare name is a shipped pad (``"helipad_1m"``). Default: the
            paper's 4 m pad.

The pad is drawn at its true size by both renderers; ``[visual] pad_scale`` and
``pad_colour_jitter`` apply to any design. Absent section (or the paper's pad): the nominal pad,
bit for bit. The draw comes from its own generator ``(seed, episode, PAD_STREAM)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from sitl_sim.render.pads import PadDesign, builtin_pad_paths, find_file, load_pad
from sitl_sim.table import Section, file_list

__all__ = ["PAD_STREAM", "PadConfig"]

PAD_STREAM = 0x5041_4421  # "PAD!"


@dataclass(frozen=True)
class PadConfig(Section):
    """The checked ``[pad]`` section (the pad files are read and checked when it is built)."""

    SECTION: ClassVar[str] = "pad"

    design: tuple[str, ...] | None = file_list(
        doc="pad file(s) configs/pads/NAME.toml (or a shipped pad's NAME), one drawn per "
        "episode; relative to the scenario file (absent: the paper's 4 m pad)"
    )
    designs: tuple[PadDesign, ...] = field(default=(), init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        where = f"{self.source}: [pad] design"
        shipped = builtin_pad_paths()
        loaded = []
        for name in self.design or ():
            path = shipped[name] if name in shipped else find_file(name, self.source, where)
            loaded.append(load_pad(path))
        object.__setattr__(self, "designs", tuple(loaded))

    def draw(self, seed: int, index: int) -> PadDesign | None:
        """Episode ``index`` of ``seed``'s pad (None: the nominal pad)."""
        if not self.designs:
            return None
        rng = np.random.default_rng([int(seed), int(index), PAD_STREAM])
        return self.designs[int(rng.integers(len(self.designs)))]
