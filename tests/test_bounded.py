"""companion.table.Bounded: a record's bounded() fields are checked on construction, in the
order they are declared, each named as its record says."""

from __future__ import annotations

from dataclasses import dataclass, replace

import pytest

from companion.table import Bounded, bounded
from sitl_sim.errors import ConfigError


@dataclass(frozen=True)
class _Record(Bounded):
    gain: float = bounded(1.0, 0.0, lo_open=True)
    limit: float = bounded(5.0, 0.0, 10.0, name="LIMIT")
    free: float = -3.0


def test_defaults_and_values_in_range_pass():
    assert _Record() == _Record(1.0, 5.0, -3.0)
    assert _Record(gain=1e-9, limit=0.0).limit == 0.0


def test_a_field_out_of_range_names_the_record_or_its_own_name():
    with pytest.raises(ConfigError, match=r"^_Record\.gain = 0\.0; expected a finite number > 0"):
        _Record(gain=0.0)
    with pytest.raises(ConfigError, match=r"^LIMIT = 11\.0; expected"):
        _Record(limit=11.0)
    with pytest.raises(ConfigError, match=r"^LIMIT = nan"):
        replace(_Record(), limit=float("nan"))


def test_the_first_declared_field_is_reported_first():
    with pytest.raises(ConfigError, match=r"^_Record\.gain"):
        _Record(gain=-1.0, limit=-1.0)
