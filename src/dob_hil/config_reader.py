"""Reading one TOML table of the config: typed getters that name the dotted field on every
error, check values against their :class:`~dob_hil.config_schema.Field` (type, bounds, choices),
and refuse unknown keys with the closest valid key and the list of valid keys.

Also what a drive profile's ``parse_options`` receives for its ``[drive.<profile>]`` table
(:data:`ConfigSection`, re-exported by :mod:`dob_hil.config`).
"""

from __future__ import annotations

import difflib
import math
import unicodedata
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.config_schema import (
    MAX_MATRIX_ENTRY,
    MAX_STRING_CHARS,
    REQUIRED,
    SectionSpec,
    section_spec,
    subsections,
)
from dob_hil.errors import ConfigError

Matrix = npt.NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
# Section reader: typed getters that name the field on every error and reject unknown keys.
# ``get(key)`` reads a key declared in :mod:`dob_hil.config_schema` (type, bounds, default);
# the explicit getters serve tables the schema does not describe (a profile's options).
# ---------------------------------------------------------------------------------------------
class _Section:
    def __init__(self, data: object, path: str, spec: SectionSpec | None = None) -> None:
        if not isinstance(data, Mapping):
            raise ConfigError(path or "<root>", f"expected a table, got {_kind(data)}")
        self.data: Mapping[str, Any] = data
        self.path = path
        self.spec = spec if spec is not None else section_spec(path)
        self.used: set[str] = set()
        self.asked: list[str] = []  # every key asked for, present or not: the valid keys

    def name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str) -> object:
        self.used.add(key)
        return self.data[key]

    def _ask(self, key: str) -> bool:
        if key not in self.asked:
            self.asked.append(key)
        return key in self.data

    def sub(self, key: str, required: bool = False) -> _Section:
        if not self._ask(key):
            if required:
                raise ConfigError(self.name(key), "missing (a required table)")
            return _Section({}, self.name(key))
        return _Section(self.raw(key), self.name(key))

    def get(self, key: str, shape: tuple[int | None, int | None] | None = None, why: str = "") -> Any:
        """The value of the schema field ``key`` of this section, checked against its Field
        (a matrix also against ``shape``, which ``why`` explains in the error)."""
        if self.spec is None:
            raise KeyError(f"{self.path} has no schema")
        f = self.spec.field(key)
        if f.default == REQUIRED:
            default: object = None
        elif f.default is None or (isinstance(f.default, str) and f.kind != "string"):
            default = None  # None, or a default described in words (computed by the parser)
        else:
            default = f.default
        present = self._ask(key)
        if not present and f.default == REQUIRED:
            raise ConfigError(self.name(key), f"missing (a required {_KIND_WORDS[f.kind]})")
        if not present:
            return default
        if f.kind == "number":
            return self.number(key, low=f.low, high=f.high, low_open=f.low_open, high_open=f.high_open)
        if f.kind == "integer":
            return self.integer(key, low=_int_or_none(f.low), high=_int_or_none(f.high))
        if f.kind == "boolean":
            return self.boolean(key, False)
        if f.kind == "string":
            return self.string(key, choices=f.choices)
        if f.kind == "strings":
            return self.strings(key)
        if f.kind == "integers":
            return self.integers(key)
        if f.kind == "numbers":
            return self.numbers(key, low=f.low, low_open=f.low_open, magnitude=f.high)
        if f.kind == "matrix":
            return parse_matrix(
                self.raw(key), self.name(key), shape, magnitude=f.high or MAX_MATRIX_ENTRY, why=why
            )
        raise AssertionError(f"unknown field kind {f.kind}")  # pragma: no cover

    def number(
        self,
        key: str,
        default: float | None = None,
        *,
        positive: bool = False,
        nonnegative: bool = False,
        below: float | None = None,
        low: float | None = None,
        high: float | None = None,
        low_open: bool = False,
        high_open: bool = False,
    ) -> float:
        if not self._ask(key):
            if default is None:
                raise ConfigError(self.name(key), "missing (a required number)")
            return default
        x = _to_float(self.raw(key), self.name(key))
        if positive:
            low, low_open = 0.0, True
        elif nonnegative:
            low, low_open = 0.0, False
        if below is not None:
            high, high_open = below, True
        _check_bounds(self.name(key), x, low, high, low_open, high_open)
        return x

    def optional_number(self, key: str, *, positive: bool = False) -> float | None:
        if not self._ask(key):
            return None
        return self.number(key, positive=positive)

    def integer(
        self, key: str, default: int | None = None, *, low: int | None = None, high: int | None = None
    ) -> int:
        if not self._ask(key):
            if default is None:
                raise ConfigError(self.name(key), "missing (a required integer)")
            return default
        value = self.raw(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(self.name(key), f"expected an integer, got {_kind(value)}")
        if low is not None and value < low:
            raise ConfigError(self.name(key), f"must be >= {low}, got {_short_int(value)}")
        if high is not None and value > high:
            raise ConfigError(self.name(key), f"must be <= {high}, got {_short_int(value)}")
        return value

    def boolean(self, key: str, default: bool) -> bool:
        if not self._ask(key):
            return default
        value = self.raw(key)
        if not isinstance(value, bool):
            raise ConfigError(self.name(key), f"expected true or false, got {_kind(value)}")
        return value

    def string(self, key: str, default: str | None = None, choices: tuple[str, ...] = ()) -> str:
        if not self._ask(key):
            if default is None:
                raise ConfigError(self.name(key), "missing (a required string)")
            return default
        value = self.raw(key)
        if not isinstance(value, str):
            raise ConfigError(self.name(key), f"expected a string, got {_kind(value)}")
        if choices and value not in choices:
            hint = _did_you_mean(value, choices)
            raise ConfigError(
                self.name(key), f"must be one of {', '.join(choices)}; got {_short_str(value)}{hint}"
            )
        _check_text(
            self.name(key), value, MAX_PATH_CHARS if key.endswith(("path", "dir")) else MAX_STRING_CHARS
        )
        return value

    def strings(self, key: str) -> tuple[str, ...] | None:
        if not self._ask(key):
            return None
        value = self.raw(key)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(self.name(key), f"expected a list of strings, got {_kind(value)}")
        for i, v in enumerate(value):
            _check_text(f"{self.name(key)}[{i}]", v, MAX_STRING_CHARS)
        return tuple(value)

    def integers(self, key: str) -> tuple[int, ...] | None:
        if not self._ask(key):
            return None
        value = self.raw(key)
        if not isinstance(value, list) or not all(
            isinstance(v, int) and not isinstance(v, bool) for v in value
        ):
            raise ConfigError(self.name(key), f"expected a list of integers, got {_kind(value)}")
        return tuple(value)

    def numbers(
        self,
        key: str,
        *,
        positive: bool = False,
        low: float | None = None,
        low_open: bool = False,
        magnitude: float | None = None,
    ) -> tuple[float, ...] | None:
        if not self._ask(key):
            return None
        arr = parse_matrix(self.raw(key), self.name(key), None, magnitude=magnitude or MAX_MATRIX_ENTRY)
        if arr.shape[0] != 1 and arr.shape[1] != 1:
            raise ConfigError(self.name(key), "expected a list of numbers")
        flat = tuple(float(v) for v in arr.ravel())
        if positive and any(v <= 0 for v in flat):
            raise ConfigError(self.name(key), "every value must be > 0")
        if low is not None:
            for i, v in enumerate(flat):
                if v < low or (low_open and v == low):
                    raise ConfigError(
                        self.name(key), f"entry [{i}] must be {'>' if low_open else '>='} {low:g}, got {v:g}"
                    )
        return flat

    def matrix(self, key: str, shape: tuple[int | None, int | None] | None = None) -> Matrix | None:
        """A 2-D float matrix. A flat list is a row vector; ``shape`` entries of None are free."""
        if not self._ask(key):
            return None
        return parse_matrix(self.raw(key), self.name(key), shape)

    def valid_keys(self) -> list[str]:
        keys = list(self.spec.keys) if self.spec is not None else []
        keys += [k for k in subsections(self.path) if k not in keys]
        keys += [k for k in self.asked if k not in keys]
        return keys

    def finish(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            key = str(unknown[0])
            valid = self.valid_keys()
            hint = _did_you_mean(key, valid)
            listing = f"; valid keys here: {', '.join(valid)}" if valid else "; this table takes no keys"
            raise ConfigError(self.name(_short_str(key, quote=False)), f"unknown key{hint}{listing}")


ConfigSection = _Section  # what a profile's parse_options receives: its [drive.<profile>] table

_KIND_WORDS = {
    "number": "number", "integer": "integer", "boolean": "boolean", "string": "string",
    "strings": "list of strings", "integers": "list of integers", "numbers": "list of numbers",
    "matrix": "matrix",
}  # fmt: skip
MAX_PATH_CHARS = 4096


def _int_or_none(x: float | None) -> int | None:
    return None if x is None else int(x)


def _did_you_mean(key: str, valid: Sequence[str]) -> str:
    close = difflib.get_close_matches(key, list(valid), n=1, cutoff=0.6)
    if not close:  # a case slip or a missing unit suffix: "Current_Limit", "current_limit"
        close = [v for v in valid if v.lower() == key.lower() or v.lower().startswith(key.lower() + "_")]
    return f" (did you mean {close[0]!r}?)" if close else ""


def _short_int(value: int) -> str:
    text = str(value) if abs(value) < 10**30 else f"an integer of {len(str(abs(value)))} digits"
    return text


def _short_str(value: str, quote: bool = True) -> str:
    text = value if len(value) <= 40 else value[:37] + "..."
    return repr(text) if quote else text.encode("unicode_escape").decode("ascii")


def _check_text(name: str, value: str, max_chars: int) -> None:
    """No control characters (NUL, escape sequences) and a bounded length in any string."""
    for i, ch in enumerate(value):
        if unicodedata.category(ch) == "Cc":
            raise ConfigError(name, f"contains a control character (U+{ord(ch):04X}) at position {i}")
    if len(value) > max_chars:
        raise ConfigError(name, f"is {len(value)} characters long; at most {max_chars}")


def _to_float(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(name, f"expected a number, got {_kind(value)}")
    try:
        x = float(value)
    except OverflowError:
        raise ConfigError(name, f"out of range: {_short_int(int(value))}") from None
    if not math.isfinite(x):
        raise ConfigError(name, f"must be finite, got {x}")
    return x


def _check_bounds(
    name: str, x: float, low: float | None, high: float | None, low_open: bool, high_open: bool
) -> None:
    if low is not None and (x < low or (low_open and x == low)):
        raise ConfigError(name, f"must be {'>' if low_open else '>='} {low:g}, got {x:g}")
    if high is not None and (x > high or (high_open and x == high)):
        raise ConfigError(name, f"must be {'<' if high_open else '<='} {high:g}, got {x:g}")


def _kind(value: object) -> str:
    if isinstance(value, bool):
        return f"boolean {value}"
    if isinstance(value, int):
        return f"number {_short_int(value)}"
    if isinstance(value, float):
        return f"number {value}"
    if isinstance(value, str):
        return f"string {_short_str(value)}"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, Mapping):
        return "a table"
    return type(value).__name__


def parse_matrix(
    value: object,
    name: str,
    shape: tuple[int | None, int | None] | None = None,
    *,
    magnitude: float = MAX_MATRIX_ENTRY,
    why: str = "",
) -> Matrix:
    """Parse a TOML number, list or list of lists into a finite 2-D float64 array.

    A flat list is a row, or a column where ``shape`` asks for as many rows as it has entries
    (``Lc = [0.75, 0.5]`` for a 2x1 gain). Every entry's magnitude is at most ``magnitude``.
    ``why`` explains ``shape`` in the error (e.g. "plant: 2 states, 1 output").
    """
    if isinstance(value, bool):
        raise ConfigError(name, f"expected a matrix of numbers, got {_kind(value)}")
    if isinstance(value, (int, float)):
        rows: list[list[object]] = [[value]]
    elif isinstance(value, list):
        if not value:
            raise ConfigError(name, "expected a matrix of numbers, got an empty list")
        if all(isinstance(r, list) for r in value):
            rows = [list(r) for r in value]
        elif any(isinstance(r, list) for r in value):
            raise ConfigError(name, "mixes numbers and rows; write a list of rows")
        else:
            rows = [list(value)]
    else:
        raise ConfigError(name, f"expected a matrix of numbers, got {_kind(value)}")
    width = len(rows[0])
    if width == 0:
        raise ConfigError(name, "has an empty row")
    for i, row in enumerate(rows):
        if len(row) != width:
            raise ConfigError(name, f"row {i} has {len(row)} entries, row 0 has {width}")
        for j, v in enumerate(row):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(name, f"entry [{i}][{j}] is {_kind(v)}, expected a number")
            try:
                x = float(v)
            except OverflowError:
                raise ConfigError(name, f"entry [{i}][{j}] out of range: {_short_int(int(v))}") from None
            if not math.isfinite(x):
                raise ConfigError(name, f"entry [{i}][{j}] must be finite, got {v}")
            if abs(x) > magnitude:
                raise ConfigError(name, f"entry [{i}][{j}] must have a magnitude <= {magnitude:g}, got {x:g}")
    arr = np.array(rows, dtype=np.float64)
    if shape is not None and arr.shape[0] == 1 and shape[0] not in (None, 1) and arr.shape[1] == shape[0]:
        arr = arr.T  # a flat list where a column is expected: ``Lc = [0.75, 0.5]``
    if shape is not None:
        want_r, want_c = shape
        if (want_r is not None and arr.shape[0] != want_r) or (want_c is not None and arr.shape[1] != want_c):
            want = f"{'k' if want_r is None else want_r}x{'k' if want_c is None else want_c}"
            because = f" ({why})" if why else ""
            raise ConfigError(name, f"expected shape {want}{because}, got {arr.shape[0]}x{arr.shape[1]}")
    return arr
