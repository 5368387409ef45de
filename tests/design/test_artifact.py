"""The Design artifact: exact JSON round trips, versioning and shape validation."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from dob_hil.design import FORMAT_VERSION, Design
from dob_hil.errors import DesignError


def _bits(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


@pytest.mark.parametrize("name", ["paper", "mimo", "delay"])
def test_json_round_trip_is_bit_exact(designs: dict[str, Design], name: str, tmp_path: Path) -> None:
    d = designs[name]
    back = Design.from_json(d.to_json())
    assert back == d
    for field in ("A", "B", "C_cont", "Phi", "Gam", "C", "Lc", "Kc", "Kdist"):
        assert _bits(getattr(back, field)) == _bits(getattr(d, field)), field
    assert back.spectral_radii == d.spectral_radii
    assert back.to_json() == d.to_json()
    path = tmp_path / "design.json"
    d.save(path)
    assert Design.load(path) == d


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None)
@given(
    Phi=hnp.arrays(np.float64, (3, 3), elements=finite),
    Lc=hnp.arrays(np.float64, (3, 1), elements=finite),
    Kdist=hnp.arrays(np.float64, (2, 3), elements=finite),
)
def test_arbitrary_float64_values_round_trip_bit_for_bit(
    designs: dict[str, Design], Phi: np.ndarray, Lc: np.ndarray, Kdist: np.ndarray
) -> None:
    """Subnormals, -0.0, 1e308: every float64 comes back with the same bits."""
    base = designs["delay"].to_dict()  # names and units; the matrices below make a 2 + 1 state design
    data = {
        **base,
        "A": [[0.0, 1.0], [0.0, -1.0]],
        "B": [[0.0], [1.0]],
        "C_cont": [[1.0, 0.0]],
        "input_delay_samples": 1,
        "state_names": ["x1", "x2", "u(k-1)"],
        "input_names": ["u"],
        "Phi": Phi.tolist(),
        "Gam": [[0.0], [0.0], [1.0]],
        "C": [[1.0, 0.0, 0.0]],
        "Lc": Lc.tolist(),
        "Kc": Kdist[:1].tolist(),
        "Kdist": Kdist[1:].tolist(),
        "spectral_radii": {k: [0.0, 0.5, 2.0] for k in ("estimator", "feedback", "dob")},
    }
    d = Design.from_dict(data)
    back = Design.from_json(d.to_json())
    assert _bits(back.Phi) == _bits(Phi)
    assert _bits(back.Lc) == _bits(Lc)
    assert _bits(back.Kdist) == _bits(Kdist[1:])


def _mutated(d: Design, **changes: Any) -> str:
    data = d.to_dict()
    data.update(changes)
    return json.dumps(data)


def test_unknown_versions_and_formats_are_refused(designs: dict[str, Design]) -> None:
    d = designs["paper"]
    with pytest.raises(DesignError, match=r"format_version: 2 is not supported \(this dob_hil reads 1\)"):
        Design.from_json(_mutated(d, format_version=FORMAT_VERSION + 1))
    with pytest.raises(DesignError, match=r"'format' must be 'dob_hil\.design'"):
        Design.from_json(_mutated(d, format="something.else"))
    with pytest.raises(DesignError, match="not valid JSON"):
        Design.from_json("{not json")


def test_wrong_shapes_are_refused_with_the_field_named(designs: dict[str, Design]) -> None:
    d = designs["paper"]
    with pytest.raises(DesignError, match=r"design\.Kdist: expected shape 1x2 .* got 1x3"):
        Design.from_json(_mutated(d, Kdist=[[1.0, 2.0, 3.0]]))
    with pytest.raises(DesignError, match=r"design\.Lc: expected shape 2x1"):
        Design.from_json(_mutated(d, Lc=[[0.75, 0.5]]))
    with pytest.raises(DesignError, match=r"design\.Phi: row 1 has 1 entries"):
        Design.from_json(_mutated(d, Phi=[[1.0, 0.0], [0.0]]))
    with pytest.raises(DesignError, match=r"design\.Phi: expected shape 4x4"):
        Design.from_json(_mutated(d, input_delay_samples=2))
    with pytest.raises(DesignError, match=r"design\.state_names: expected 2 names, got 1"):
        Design.from_json(_mutated(d, state_names=["x"]))
    with pytest.raises(DesignError, match=r"design\.spectral_radii\.dob: expected 2 magnitudes"):
        Design.from_json(_mutated(d, spectral_radii={"estimator": [0, 0], "feedback": [0, 0], "dob": [0]}))


def test_missing_unknown_and_non_numeric_fields_are_refused(designs: dict[str, Design]) -> None:
    d = designs["paper"]
    data = d.to_dict()
    del data["Kc"]
    with pytest.raises(DesignError, match=r"missing key.*Kc"):
        Design.from_json(json.dumps(data))
    with pytest.raises(DesignError, match=r"unknown key.*Kq"):
        Design.from_json(_mutated(d, Kq=[[1.0]]))
    with pytest.raises(DesignError, match=r"design\.Kc: row 0 holds 'x'"):
        Design.from_json(_mutated(d, Kc=[["x", 1.0]]))
    with pytest.raises(DesignError, match=r"design\.period_ns: must be a positive integer"):
        Design.from_json(_mutated(d, period_ns=300000.5))
    with pytest.raises(DesignError, match=r"design\.Kc: every entry must be finite"):
        Design.from_dict({**d.to_dict(), "Kc": [[float("nan"), 1.0]]})


def test_arrays_are_read_only_and_the_dataclass_is_frozen(designs: dict[str, Design]) -> None:
    d = designs["paper"]
    with pytest.raises(ValueError, match="read-only"):
        d.Kc[0, 0] = 1.0
    with pytest.raises(AttributeError):
        d.name = "other"  # type: ignore[misc]
    assert d.Phi.dtype == np.float64 and d.Phi.ndim == 2


def test_require_stable_reports_the_offending_matrix(designs: dict[str, Design]) -> None:
    d = designs["paper"]
    d.require_stable(dob_enabled=True)
    bad = Design.from_dict({**d.to_dict(), "spectral_radii": {**d.spectral_radii, "dob": [0.5, 1.07]}})
    bad.require_stable(dob_enabled=False)
    with pytest.raises(DesignError, match=r"^dob: rho\(Phi - Phi Lc C - Gam Kdist Lc C\) = 1\.07 >= 1$"):
        bad.require_stable(dob_enabled=True)
