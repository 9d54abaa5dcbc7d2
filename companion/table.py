"""One typed reader for the TOML tables of every configuration file (scenario, suite, vehicle,
simulation, expert, companion): a section is a frozen dataclass whose fields declare, once, each
key's type, unit, default, range and meaning (as PX4's ``module.yaml``); the reader, the checks and
``docs/config_keys.md`` all come from them.

Declare a section::

    @dataclass(frozen=True)
    class WindConfig(Section):
        SECTION: ClassVar[str] = "wind"
        speed_m_s: tuple[float, float] = span(unit="m/s", lo=0.0, doc="mean wind speed")
        turbulence: str = choice("none", TURBULENCE_LEVELS, doc="Dryden level")

and read it with ``WindConfig.from_table(table, where)``; built in code, it is checked the
same way (:class:`Section`'s ``__post_init__``). Rules, the same for every section:

* a key left out takes the field's default (its documented nominal value); a field declared
  without one (:data:`REQUIRED`) must be given;
* an unknown key, a value of the wrong type and a value out of range are each a
  :class:`ConfigError` (or the section's own ``ERROR``, a subclass: the companion's
  ``CompanionError``) ``"<where>: [section] key = <got>; expected <what>"``.

Field kinds: :func:`span` (``[lo, hi]`` of numbers, drawn per episode; a single number ``x`` in
the file means ``[x, x]``), :func:`integer_span` (likewise),
:func:`number`, :func:`vector` (``size`` numbers), :func:`probability`, :func:`integer`,
:func:`choice` (a string among choices)
and :func:`choice_list` (a non-empty list of them), :func:`file_list` (file names); a
command-line option (:func:`companion.options.option`) is also a ``text`` or ``boolean`` key.

It lives in ``companion/`` (beside ``files.py`` and ``options.py``) because the companion
installs on a board without the simulator, and the simulator, the expert and training import
it from here.
:func:`check_tables` checks a file's sections; :func:`read_spread` reads a record whose keys
are spread over several tables (each key's ``table``); ``python -m tools.config_keys`` prints
every file's keys from :func:`declared_keys` (``docs/config_keys.md``).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Iterable
from typing import Any, ClassVar

__all__ = [
    "REQUIRED",
    "Bounded",
    "ConfigError",
    "Key",
    "Section",
    "amount",
    "bounded",
    "check_number",
    "check_section",
    "check_tables",
    "choice",
    "choice_list",
    "declared_keys",
    "file_list",
    "integer",
    "integer_span",
    "key_field",
    "number",
    "number_text",
    "probability",
    "read_section",
    "read_spread",
    "read_values",
    "section_dict",
    "section_keys",
    "span",
    "vector",
]


class ConfigError(ValueError):
    """A configuration file or value is missing, malformed or out of range.

    The message names the file (when there is one), the field and what was expected.
    """


REQUIRED: Any = dataclasses.MISSING
"""The default of a key that has no nominal value and must be given."""

_META = "visland.key"
_NUMBER, _INTEGER, _SPAN, _INT_SPAN, _CHOICE, _CHOICES = (
    "number",
    "integer",
    "span",
    "integer span",
    "choice",
    "choice list",
)
_FILES = "file list"
_VECTOR = "vector"
_TEXT, _BOOL = "text", "boolean"


def number_text(x: float) -> str:
    """A bound as written in errors and docs: ``10``, ``0.05``, ``2147483647``."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


@dataclasses.dataclass(frozen=True)
class Key:
    """How one key of a section is typed and checked (a field's metadata).

    Attributes:
        kind: ``number``, ``integer``, ``span``, ``integer span``, ``vector``, ``choice``,
            ``choice list``, ``file list``, ``text`` or ``boolean``.
        unit: the unit (``"1"``: dimensionless).
        doc: what the key means (one line, for the docs table).
        lo, hi: inclusive bounds (None: unbounded); ``lo_open`` makes ``lo`` exclusive.
        noun: how the expected value is named in an error (``"a probability"``, ``"factors"``).
        ends: the names of a span's two ends (``("lo", "hi")``, ``("start", "end")``).
        strict: a span needs ``lo < hi`` (not ``<=``).
        finite_hi: a span's upper end must be finite (False: ``inf`` allowed, "for good").
        choices: the allowed strings of a choice.
        size: how many numbers a vector holds.
        table: the table the key is read from, where one record's keys are spread over
            several tables of a file (``configs/expert.toml``); empty: the record's section.
    """

    kind: str
    unit: str
    doc: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    noun: str = ""
    ends: tuple[str, str] = ("lo", "hi")
    strict: bool = False
    finite_hi: bool = True
    choices: tuple[str, ...] = ()
    size: int = 0
    table: str = ""

    # ------------------------------------------------------------------ reading

    def convert(self, value: Any) -> Any:
        """``value`` (as TOML parsed it) typed, or None when it has the wrong type."""
        if self.kind == _NUMBER:
            return float(value) if _is_number(value) else None
        if self.kind == _INTEGER:
            return value if _is_int(value) else None
        if self.kind == _VECTOR:
            good = isinstance(value, list) and len(value) == self.size
            return tuple(float(v) for v in value) if good and all(map(_is_number, value)) else None
        if self.kind in (_SPAN, _INT_SPAN):
            ok = _is_int if self.kind == _INT_SPAN else _is_number
            if ok(value):  # a scalar x is the span [x, x] (a fixed value, every episode)
                value = [value, value]
            if not (isinstance(value, list) and len(value) == 2 and all(map(ok, value))):
                return None
            cast = int if self.kind == _INT_SPAN else float
            return cast(value[0]), cast(value[1])
        if self.kind == _CHOICE:
            return value if isinstance(value, str) and value in self.choices else None
        if self.kind == _TEXT:
            return value if isinstance(value, str) else None
        if self.kind == _BOOL:
            return value if isinstance(value, bool) else None
        if self.kind == _FILES:  # one name is a list of one
            names = [value] if isinstance(value, str) else value
            ok = isinstance(names, list) and names and all(isinstance(v, str) for v in names)
            return tuple(names) if ok and all(v.strip() for v in names) else None
        good = isinstance(value, list) and value and all(v in self.choices for v in value)
        return tuple(value) if good and all(isinstance(v, str) for v in value) else None

    def type_phrase(self) -> str:
        """What a value of this key looks like (the "expected" of a wrong type)."""
        a, b = self.ends
        if self.kind == _SPAN:
            return f"[{a}, {b}] (two numbers), or one number x for [x, x]"
        if self.kind == _INT_SPAN:
            return f"[{a}, {b}] (two integers), or one integer x for [x, x]"
        if self.kind == _VECTOR:
            return f"a list of {self.size} numbers"
        return self.expected()

    # ------------------------------------------------------------------ checking

    def _above_lo(self, x: float) -> bool:
        return self.lo is None or (x > self.lo if self.lo_open else x >= self.lo)

    def _in_bounds(self, x: float) -> bool:
        return math.isfinite(x) and self._above_lo(x) and (self.hi is None or x <= self.hi)

    def in_range(self, value: Any) -> bool:
        if self.kind in (_TEXT, _BOOL):
            return isinstance(value, str if self.kind == _TEXT else bool)
        if self.kind == _CHOICE:
            return value in self.choices
        if self.kind == _CHOICES:
            return bool(value) and all(v in self.choices for v in value)
        if self.kind == _FILES:
            return bool(value)
        if self.kind == _VECTOR:
            return len(value) == self.size and all(self._in_bounds(v) for v in value)
        if self.kind in (_NUMBER, _INTEGER):
            return self._in_bounds(value)
        a, b = value
        ordered = a < b if self.strict else a <= b
        return (
            math.isfinite(a)
            and (math.isfinite(b) or (not self.finite_hi and b == math.inf))
            and ordered
            and self._above_lo(a)
            and (self.hi is None or b <= self.hi)
        )

    def bounds(self) -> str:
        """The range as written in errors and the docs: ``0 <= lo <= hi <= 10``,
        ``in [0, 1]``, ``>= 0``, ``one of [...]``."""
        if self.kind == _CHOICE:
            return f"one of {list(self.choices)}"
        if self.kind == _CHOICES:
            return f"a non-empty list of {list(self.choices)}"
        if self.kind == _FILES:
            return "a file name, or a non-empty list of them"
        if self.kind in (_TEXT, _BOOL):
            return "a string" if self.kind == _TEXT else "true or false"
        lo_op = "<" if self.lo_open else "<="
        if self.kind == _VECTOR:
            return (
                f"{self.size} numbers, each "
                + Key(_NUMBER, "", "", self.lo, self.hi, self.lo_open).bounds()
            )
        if self.kind in (_NUMBER, _INTEGER):
            if self.lo is not None and self.hi is not None and not self.lo_open:
                return f"in [{number_text(self.lo)}, {number_text(self.hi)}]"
            parts = (
                [f"{'>' if self.lo_open else '>='} {number_text(self.lo)}"]
                if self.lo is not None
                else []
            )
            parts += [f"<= {number_text(self.hi)}"] if self.hi is not None else []
            return " and ".join(parts) or "finite"
        a, b = self.ends
        chain = f"{a} {'<' if self.strict else '<='} {b}"
        if self.lo is not None:
            chain = f"{number_text(self.lo)} {lo_op} {chain}"
        if self.hi is not None:
            chain = f"{chain} <= {number_text(self.hi)}"
        return chain

    def expected(self) -> str:
        """The "expected" of a value out of range."""
        unit = f" ({self.unit})" if self.unit not in ("", "1") else ""
        if self.kind in (_CHOICE, _CHOICES, _FILES, _TEXT, _BOOL):
            return self.bounds()
        if self.kind == _VECTOR:
            return f"{self.bounds()}{unit}"
        if self.kind in (_NUMBER, _INTEGER):
            bounds = self.bounds()
            return f"{self.noun}{'' if bounds == 'finite' else ' ' + bounds}{unit}"
        a, b = self.ends
        noun = f"{self.noun} " if self.noun else ""
        return f"{noun}[{a}, {b}] with {self.bounds()}{unit}"


def key_field(key: Key, default: Any, **metadata: Any) -> Any:
    """A dataclass field declared by ``key`` (``metadata``: more of the field's metadata, as
    a command-line option's help)."""
    return dataclasses.field(default=default, metadata={_META: key, **metadata})


def span(
    default: tuple[float, float] | None = REQUIRED,
    *,
    unit: str,
    doc: str,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    noun: str = "finite",
    ends: tuple[str, str] = ("lo", "hi"),
    strict: bool = False,
    finite_hi: bool = True,
) -> Any:
    """A ``[lo, hi]`` key of numbers (None default: absent = off)."""
    key = Key(_SPAN, unit, doc, lo, hi, lo_open, noun, ends, strict, finite_hi)
    return key_field(key, default)


def amount(*, unit: str, hi: float, doc: str) -> Any:
    """A ``[lo, hi]`` key of a quantity in ``[0, hi]`` that is off (``[0, 0]``) unless given."""
    return span((0.0, 0.0), unit=unit, lo=0.0, hi=hi, doc=doc)


def integer_span(default: tuple[int, int], *, unit: str, doc: str, lo: int, hi: int) -> Any:
    """A ``[lo, hi]`` key of integers, inclusive."""
    return key_field(Key(_INT_SPAN, unit, doc, lo, hi, noun="integers"), default)


def number(
    default: float = REQUIRED,
    *,
    unit: str,
    doc: str,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    noun: str = "a number",
    table: str = "",
) -> Any:
    """A number key (an integer in the file is taken as a float)."""
    return key_field(Key(_NUMBER, unit, doc, lo, hi, lo_open, noun=noun, table=table), default)


def vector(
    default: tuple[float, ...] = REQUIRED,
    *,
    size: int,
    unit: str,
    doc: str,
    lo: float | None = None,
    hi: float | None = None,
) -> Any:
    """A key of ``size`` numbers, each within ``[lo, hi]`` (a tuple of floats once read)."""
    return key_field(Key(_VECTOR, unit, doc, lo, hi, noun="numbers", size=size), default)


def probability(doc: str) -> Any:
    """A probability in [0, 1], 0 (off) when left out."""
    return number(0.0, unit="1", doc=doc, lo=0.0, hi=1.0, noun="a probability")


def integer(
    default: int = REQUIRED,
    *,
    unit: str,
    doc: str,
    lo: int,
    hi: int | None = None,
    table: str = "",
) -> Any:
    """An integer key."""
    return key_field(Key(_INTEGER, unit, doc, lo, hi, noun="an integer", table=table), default)


def choice(default: str, choices: Iterable[str], *, doc: str) -> Any:
    """A string key among ``choices`` (:data:`REQUIRED`: no default)."""
    return key_field(Key(_CHOICE, "", doc, choices=tuple(choices)), default)


def choice_list(default: tuple[str, ...], choices: Iterable[str], *, doc: str) -> Any:
    """A non-empty list of strings among ``choices`` (a tuple once read)."""
    return key_field(Key(_CHOICES, "", doc, choices=tuple(choices)), default)


def file_list(*, doc: str) -> Any:
    """A file name or a non-empty list of them (a tuple once read; absent: None, off). The
    section resolves and checks the files (relative to its scenario file)."""
    return key_field(Key(_FILES, "", doc), None)


# --------------------------------------------------------------------------- reading


@dataclasses.dataclass(frozen=True)
class Section:
    """Base of a section dataclass: ``SECTION`` names its table, ``ERROR`` the error it raises
    (a :class:`ConfigError`), ``source`` where it was read (for errors; keyword-only, not
    compared). Built in code or read by :meth:`from_table`, it
    is checked against its declarations; a subclass with cross-key checks calls
    ``super().__post_init__()`` first."""

    SECTION: ClassVar[str] = ""
    ERROR: ClassVar[type[ConfigError]] = ConfigError
    source: str = dataclasses.field(default="<memory>", compare=False, kw_only=True)

    def __post_init__(self) -> None:
        check_section(self)

    def to_dict(self) -> dict[str, Any]:
        """The keys as a TOML-like dict (what logs record of the section)."""
        return section_dict(self)

    @classmethod
    def from_table(cls, table: Any, where: str) -> Any:
        """This section read from ``table`` (a TOML table of file ``where``)."""
        return read_section(cls, table, where)


def declared_keys(cls: type) -> dict[str, tuple[dataclasses.Field, Key]]:
    """``{name: (field, Key)}`` of every declared key of ``cls``, in declaration order."""
    return {f.name: (f, f.metadata[_META]) for f in dataclasses.fields(cls) if _META in f.metadata}


def section_keys(cls: type) -> tuple[str, ...]:
    """The keys of section class ``cls``, in declaration order."""
    return tuple(declared_keys(cls))


def read_values(
    cls: type,
    table: Any,
    where: str,
    section: str | None = None,
    names: Iterable[str] | None = None,
) -> dict[str, Any]:
    """The typed values of the keys ``table`` gives (defaults are the dataclass's own);
    ``names``: only these keys of ``cls`` belong to this table (None: all of them).

    Raises:
        ConfigError: (``cls.ERROR``) ``table`` is not a table, or has an unknown key, or lacks a
            :data:`REQUIRED` one, or a value has the wrong type (naming ``where``, the section
            and the key). Ranges are checked by :func:`check_section` when ``cls`` is built.
    """
    section = section or cls.SECTION  # type: ignore[attr-defined]
    error = getattr(cls, "ERROR", ConfigError)
    if not isinstance(table, dict):
        raise error(f"{where}: [{section}] must be a table, got {table!r}")
    keys = declared_keys(cls)
    if names is not None:
        keys = {name: keys[name] for name in names}
    unknown = sorted(set(table) - set(keys))
    if unknown:
        near = [m for u in unknown for m in difflib.get_close_matches(u, keys, 1)]
        hint = f"did you mean {near[0]!r}?" if near else "typo?"
        raise error(
            f"{where}: [{section}] unknown key(s) {unknown}; expected {list(keys)} ({hint})"
        )
    values: dict[str, Any] = {}
    for name, (f, key) in keys.items():
        if name not in table:
            if f.default is REQUIRED:
                raise error(
                    f"{where}: [{section}] missing key {name!r}; expected {key.type_phrase()}"
                )
            continue
        value = key.convert(table[name])
        if value is None:
            raise error(
                f"{where}: [{section}] {name} = {table[name]!r}; expected {key.type_phrase()}"
            )
        values[name] = value
    return values


def check_tables(
    data: Any,
    where: str,
    known: Iterable[str],
    required: Iterable[str] = (),
    error: type[ConfigError] = ConfigError,
) -> None:
    """``data`` (a parsed TOML file) holds only the ``known`` tables and each ``required`` one.

    Raises:
        ConfigError: (``error``) ``"<where>: unknown section(s) ['[wnd]']; expected [...]"`` or
            ``"<where>: missing table [name]"``.
    """
    known = list(known)
    if not isinstance(data, dict):
        raise error(f"{where}: expected a table of sections {known}, got {data!r}")
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise error(
            f"{where}: unknown section(s) {['[' + s + ']' for s in unknown]}; "
            f"expected {['[' + s + ']' for s in known]} (typo?)"
        )
    for name in required:
        if not isinstance(data.get(name), dict):
            raise error(f"{where}: missing table [{name}]")


def read_spread(cls: type, data: Any, where: str) -> Any:
    """``cls`` read from a file whose tables each hold some of its keys (each key's
    ``table``, as ``configs/expert.toml``'s ``[mpc]``, ``[descent]``, ...). A table left out
    takes its keys' defaults; one with a :data:`REQUIRED` key must be given."""
    tables: dict[str, list[str]] = {}
    required: set[str] = set()
    for name, (f, key) in declared_keys(cls).items():
        tables.setdefault(key.table, []).append(name)
        if f.default is REQUIRED:
            required.add(key.table)
    check_tables(data, where, tables, required, getattr(cls, "ERROR", ConfigError))
    values: dict[str, Any] = {}
    for table, names in tables.items():
        values.update(read_values(cls, data.get(table, {}), where, table, names))
    return cls(**values, source=where)


def read_section(cls: type, table: Any, where: str) -> Any:
    """``cls`` (a section class: ``SECTION`` and a ``source`` field) read from ``table``."""
    return cls(**read_values(cls, table, where), source=where)


def check_section(obj: Any, section: str | None = None) -> None:
    """Check every declared key of ``obj`` (a section dataclass) against its range.

    Raises:
        ConfigError: (the section's ``ERROR``) ``"<obj.source>: [section] key = <got>;
            expected <range>"``.
    """
    section = section or type(obj).SECTION
    for name, (_f, key) in declared_keys(type(obj)).items():
        value = getattr(obj, name)
        if value is None or key.in_range(value):
            continue
        listed = isinstance(value, tuple) and key.kind in (_SPAN, _INT_SPAN, _VECTOR)
        got = f"[{', '.join(map(str, value))}]" if listed else repr(value)
        raise getattr(type(obj), "ERROR", ConfigError)(
            f"{obj.source}: [{key.table or section}] {name} = {got}; expected {key.expected()}"
        )


def check_number(
    name: str, value: Any, lo: float | None = None, hi: float | None = None, *, lo_open=False
) -> None:
    """Check one value of a record that is not a scenario section (an autopilot's parameter
    table, an episode's drawn factors) by a :class:`Key`'s rules: a finite number within
    ``[lo, hi]`` (``lo_open``: above ``lo``; None: unbounded).

    Raises:
        ConfigError: ``"<name> = <got>; expected a finite number <bounds>"``.
    """
    key = Key(_NUMBER, "1", "", lo=lo, hi=hi, lo_open=lo_open, noun="a finite number")
    if not (_is_number(value) and key.in_range(value)):
        raise ConfigError(f"{name} = {value!r}; expected {key.expected()}")


_BOUNDS = "visland.bounds"


def bounded(
    default: float,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    name: str | None = None,
) -> Any:
    """A number field of a :class:`Bounded` record, checked by :func:`check_number` within
    ``[lo, hi]`` on construction; ``name`` names it in the error (None: ``Class.field``)."""
    return dataclasses.field(default=default, metadata={_BOUNDS: (lo, hi, lo_open, name)})


class Bounded:
    """Base of a dataclass that is not a scenario section (an autopilot's parameter table, an
    episode's drawn factors) whose :func:`bounded` fields are checked on construction, in the
    order they are declared.

    Raises:
        ConfigError: ``"<name> = <got>; expected a finite number <bounds>"``.
    """

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            if _BOUNDS in f.metadata:
                lo, hi, lo_open, name = f.metadata[_BOUNDS]
                label = name or f"{type(self).__name__}.{f.name}"
                check_number(label, getattr(self, f.name), lo, hi, lo_open=lo_open)


def section_dict(obj: Any, *, drop_none: bool = False) -> dict[str, Any]:
    """The declared keys of ``obj`` as a TOML-like dict (tuples as lists); ``drop_none``
    leaves out the keys that are off."""
    out: dict[str, Any] = {}
    for name in declared_keys(type(obj)):
        value = getattr(obj, name)
        if value is None and drop_none:
            continue
        out[name] = list(value) if isinstance(value, tuple) else value
    return out
