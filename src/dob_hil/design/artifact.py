"""The design artifact: everything the run-time controller, the logger and the analysis need, as a
frozen, validated, versioned value with an exact JSON form.

JSON: one object ``{"format": "dob_hil.design", "format_version": 1, ...}`` with matrices as nested
lists of numbers. Python's ``json`` writes each float64 with ``repr`` (the shortest string that reads
back to the same double), so every matrix round-trips bit for bit. Unknown versions, missing or extra
keys, non-finite numbers and wrong shapes are refused with :class:`DesignError` naming the field.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from dob_hil.design.discretize import disturbance_input_matrix
from dob_hil.design.linalg import Matrix
from dob_hil.design.theorem1 import unstable_parts
from dob_hil.errors import DesignError

FORMAT_NAME = "dob_hil.design"
FORMAT_VERSION = 1
RADII_KEYS = ("estimator", "feedback", "dob")
_MATRIX_FIELDS = ("A", "B", "C_cont", "Phi", "Gam", "C", "Lc", "Kc", "Kdist")
_NAME_FIELDS = ("state_names", "input_names", "output_names")


def _frozen_matrix(value: object, name: str) -> Matrix:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DesignError(f"design.{name}: expected a matrix of numbers") from None
    if arr.ndim != 2:
        raise DesignError(f"design.{name}: expected a 2-D matrix, got {arr.ndim} dimension(s)")
    if not np.all(np.isfinite(arr)):
        raise DesignError(f"design.{name}: every entry must be finite")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Design:
    """A controller design for an (augmented) discrete plant ``x(k+1) = Phi x + Gam u, y = C x``.

    Dimensions: n = ``n_plant_states``, d = ``input_delay_samples``, m inputs, p outputs and the
    augmented state dimension N = n + d m (x_aug = [x; u(k-d); ...; u(k-1)]). ``A`` (n x n), ``B``
    (n x m), ``C_cont`` (p x n) are the continuous plant; ``Phi`` (N x N), ``Gam`` (N x m), ``C``
    (p x N) the ZOH-discretised, delay-augmented one; ``Lc`` (N x p) the current-estimator gain,
    ``Kc`` (m x N) the state feedback, ``Kdist`` (m x N) the DOB gain. ``state_names`` has N entries.
    ``spectral_radii`` holds the sorted eigenvalue magnitudes of Phi - Phi Lc C ("estimator"),
    Phi - Gam Kc ("feedback") and Phi - Phi Lc C - Gam Kdist Lc C ("dob"). ``gain_sources`` says how
    Lc, Kc and Kdist were obtained. Arrays are float64, 2-D and read-only.
    """

    format_version: int
    name: str
    period_ns: int
    A: Matrix
    B: Matrix
    C_cont: Matrix
    Phi: Matrix
    Gam: Matrix
    C: Matrix
    Lc: Matrix
    Kc: Matrix
    Kdist: Matrix
    n_plant_states: int
    input_delay_samples: int
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    input_unit: str
    output_unit: str
    spectral_radii: dict[str, list[float]]
    gain_sources: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.format_version != FORMAT_VERSION:
            raise DesignError(
                f"design.format_version: {self.format_version!r} is not supported "
                f"(this dob_hil reads {FORMAT_VERSION})"
            )
        for name in _MATRIX_FIELDS:
            object.__setattr__(self, name, _frozen_matrix(getattr(self, name), name))
        if not isinstance(self.period_ns, int) or isinstance(self.period_ns, bool) or self.period_ns <= 0:
            raise DesignError(f"design.period_ns: must be a positive integer, got {self.period_ns!r}")
        for name in ("n_plant_states", "input_delay_samples"):
            v, low = getattr(self, name), (1 if name == "n_plant_states" else 0)
            if not isinstance(v, int) or isinstance(v, bool) or v < low:
                raise DesignError(f"design.{name}: must be an integer >= {low}, got {v!r}")
        for name in _NAME_FIELDS:
            object.__setattr__(self, name, tuple(str(s) for s in getattr(self, name)))
        n, d = self.n_plant_states, self.input_delay_samples
        m, p = self.B.shape[1], self.C_cont.shape[0]
        N = n + d * m
        want = {
            "A": (n, n),
            "B": (n, m),
            "C_cont": (p, n),
            "Phi": (N, N),
            "Gam": (N, m),
            "C": (p, N),
            "Lc": (N, p),
            "Kc": (m, N),
            "Kdist": (m, N),
        }
        for name, shape in want.items():
            got = getattr(self, name).shape
            if got != shape:
                raise DesignError(
                    f"design.{name}: expected shape {shape[0]}x{shape[1]} (n={n}, m={m}, p={p}, N={N}), "
                    f"got {got[0]}x{got[1]}"
                )
        for name, count in (("state_names", N), ("input_names", m), ("output_names", p)):
            if len(getattr(self, name)) != count:
                raise DesignError(f"design.{name}: expected {count} names, got {len(getattr(self, name))}")
        radii = self.spectral_radii
        if not isinstance(radii, dict) or sorted(radii) != sorted(RADII_KEYS):
            raise DesignError(f"design.spectral_radii: expected the keys {', '.join(RADII_KEYS)}")
        clean: dict[str, list[float]] = {}
        for key in RADII_KEYS:
            vals = radii[key]
            if not isinstance(vals, (list, tuple)) or len(vals) != N:
                raise DesignError(f"design.spectral_radii.{key}: expected {N} magnitudes")
            try:
                clean[key] = [float(v) for v in vals]
            except (TypeError, ValueError):
                raise DesignError(f"design.spectral_radii.{key}: expected numbers") from None
            if not all(math.isfinite(v) and v >= 0.0 for v in clean[key]):
                raise DesignError(f"design.spectral_radii.{key}: magnitudes must be finite and >= 0")
        object.__setattr__(self, "spectral_radii", clean)
        object.__setattr__(self, "gain_sources", {str(k): str(v) for k, v in dict(self.gain_sources).items()})

    # ---- derived quantities ---------------------------------------------------------------
    @property
    def n_states(self) -> int:
        """N, the augmented state dimension n + d m."""
        return int(self.Phi.shape[0])

    @property
    def n_inputs(self) -> int:
        return int(self.Gam.shape[1])

    @property
    def n_outputs(self) -> int:
        return int(self.C.shape[0])

    @property
    def period_s(self) -> float:
        return self.period_ns * 1e-9

    @property
    def Gam_w(self) -> Matrix:
        """How an input disturbance at the plant's own input (after the delay) enters x_aug."""
        return disturbance_input_matrix(self.Phi, self.Gam, self.n_plant_states, self.input_delay_samples)

    @property
    def Kdist_Lc(self) -> Matrix:
        """Kdist Lc (m x p): the only way Kdist reaches the loop (u_dist = -Kdist Lc (y - C x_bar))."""
        return np.asarray(self.Kdist @ self.Lc, dtype=np.float64)

    def require_stable(self, dob_enabled: bool) -> None:
        """Raise DesignError unless the estimator, the feedback and (DOB on) the dob matrix are stable."""
        problems = unstable_parts(self.spectral_radii, dob_enabled)
        if problems:
            raise DesignError("; ".join(problems))

    # ---- equality ---------------------------------------------------------------------------
    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Design):
            return NotImplemented
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray):
                if a.shape != b.shape or a.tobytes() != b.tobytes():
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    # ---- JSON -------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"format": FORMAT_NAME}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                out[f.name] = v.tolist()
            elif isinstance(v, tuple):
                out[f.name] = list(v)
            elif isinstance(v, dict):
                out[f.name] = {k: (list(x) if isinstance(x, list) else x) for k, x in v.items()}
            else:
                out[f.name] = v
        return out

    def to_json(self) -> str:
        """Versioned JSON; floats written with repr so they read back bit for bit."""
        return json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n"

    @classmethod
    def from_dict(cls, data: object) -> Design:
        if not isinstance(data, dict):
            raise DesignError("design JSON: expected an object at the top level")
        if data.get("format") != FORMAT_NAME:
            raise DesignError(f"design JSON: 'format' must be {FORMAT_NAME!r}, got {data.get('format')!r}")
        version = data.get("format_version")
        if version != FORMAT_VERSION or isinstance(version, bool):
            raise DesignError(
                f"design.format_version: {version!r} is not supported (this dob_hil reads {FORMAT_VERSION})"
            )
        names = [f.name for f in fields(cls)]
        missing = [k for k in names if k not in data and k != "gain_sources"]
        if missing:
            raise DesignError(f"design JSON: missing key(s) {', '.join(missing)}")
        unknown = sorted(set(data) - set(names) - {"format"})
        if unknown:
            raise DesignError(f"design JSON: unknown key(s) {', '.join(unknown)}")
        kwargs: dict[str, Any] = {k: data[k] for k in names if k in data}
        for name in _MATRIX_FIELDS:
            kwargs[name] = _parse_json_matrix(data[name], name)
        for name in ("name", "input_unit", "output_unit"):
            if not isinstance(data[name], str):
                raise DesignError(f"design.{name}: expected a string")
        for name in _NAME_FIELDS:
            if not isinstance(data[name], list) or not all(isinstance(s, str) for s in data[name]):
                raise DesignError(f"design.{name}: expected a list of strings")
        for name in ("spectral_radii", "gain_sources"):
            if name in data and not isinstance(data[name], dict):
                raise DesignError(f"design.{name}: expected an object")
        return cls(**kwargs)

    @classmethod
    def from_json(cls, text: str) -> Design:
        """Parse :meth:`to_json` output; DesignError for anything malformed."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DesignError(f"design JSON: not valid JSON: {exc}") from None
        return cls.from_dict(data)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_json(), encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> Design:
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise DesignError(f"{p}: cannot read design file: {exc}") from None
        return cls.from_json(text)


def _parse_json_matrix(value: object, name: str) -> Matrix:
    if not isinstance(value, list) or not value or not all(isinstance(r, list) for r in value):
        raise DesignError(f"design.{name}: expected a non-empty list of rows")
    width = len(value[0])
    for i, row in enumerate(value):
        if len(row) != width:
            raise DesignError(f"design.{name}: row {i} has {len(row)} entries, row 0 has {width}")
        for v in row:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise DesignError(f"design.{name}: row {i} holds {v!r}, expected numbers")
    return _frozen_matrix(value, name)
