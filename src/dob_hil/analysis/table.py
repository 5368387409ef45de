"""The metrics of one or more logs as a text table: one row per metric, one column per log."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

Row = tuple[str, Callable[[dict[str, Any]], str]]
NONE = "-"


def _num(value: Any, fmt: str = ".4g", scale: float = 1.0) -> str:
    if value is None:
        return NONE
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    return format(value * scale, fmt)


def _dist(key: str, part: str) -> Callable[[dict[str, Any]], str]:
    return lambda m: _num((m.get(key) or {}).get(part), ".1f")


def _bus(part: str) -> Callable[[dict[str, Any]], str]:
    def get(m: dict[str, Any]) -> str:
        load = m.get("bus_load")
        if load is None:
            return NONE
        if part in ("worst_case", "nominal"):
            return f"{100.0 * load[part]:.1f} %"
        return _num(load[part], ".3f")

    return get


def _state_error(i: int) -> Callable[[dict[str, Any]], str]:
    def get(m: dict[str, Any]) -> str:
        errors = m["estimation_error_rms"]
        return _num(errors[i]) if errors and i < len(errors) else NONE

    return get


def _axis(key: str, j: int, fmt: str = ".4g") -> Callable[[dict[str, Any]], str]:
    """Entry ``j`` of a per-output/per-input list (``-`` where a log has none)."""

    def get(m: dict[str, Any]) -> str:
        values = m.get(key)
        return _num(values[j], fmt) if values and j < len(values) else NONE

    return get


def _axes(metrics: list[dict[str, Any]], key: str) -> int:
    """The largest number of axes of ``key`` among the logs: rows per axis only beyond one."""
    n = max((len(m.get(key) or []) for m in metrics), default=0)
    return n if n > 1 else 0


def _percent(key: str) -> Callable[[dict[str, Any]], str]:
    return lambda m: NONE if m[key] is None else f"{100.0 * m[key]:.2f} %"


def _rows(metrics: list[dict[str, Any]]) -> list[Row]:
    rows: list[Row] = [
        ("DOB", lambda m: "on" if m["dob_enabled"] else "off"),
        ("mode", lambda m: str(m["mode"])),
        ("window from [s]", lambda m: _num(m["window_start_s"], ".4f")),
        ("samples", lambda m: _num(m["samples"])),
        ("duration [s]", lambda m: _num(m["duration_s"], ".4f")),
        ("tracking error rms", lambda m: _num(m["tracking_error_rms"])),
        ("tracking error max", lambda m: _num(m["tracking_error_max"])),
        ("  against", lambda m: str(m["tracking_error_source"])),
    ]
    for j in range(_axes(metrics, "tracking_error_rms_per_output")):  # several outputs: each one
        rows.append((f"tracking error rms output {j + 1}", _axis("tracking_error_rms_per_output", j)))
        rows.append((f"tracking error max output {j + 1}", _axis("tracking_error_max_per_output", j)))
    rows += [
        ("disturbance w rms [A]", lambda m: _num(m["disturbance_rms"])),
        ("w + u_dist rms [A]", lambda m: _num(m["disturbance_estimate_error_rms"])),
        ("estimate gain -u_dist/w", lambda m: _num(m["disturbance_estimate_gain"], ".3f")),
    ]
    for j in range(_axes(metrics, "disturbance_rms_per_input")):  # several inputs: each one
        rows += [
            (f"disturbance w rms input {j + 1} [A]", _axis("disturbance_rms_per_input", j)),
            (f"w + u_dist rms input {j + 1} [A]", _axis("disturbance_estimate_error_rms_per_input", j)),
            (f"estimate gain input {j + 1}", _axis("disturbance_estimate_gain_per_input", j, ".3f")),
            (f"current rms input {j + 1} [A]", _axis("current_rms_A_per_input", j)),
            (f"current max input {j + 1} [A]", _axis("current_max_A_per_input", j)),
        ]
    n_states = max((len(m["estimation_error_rms"] or []) for m in metrics), default=0)
    for i in range(n_states):
        rows.append((f"state {i} error rms", _state_error(i)))
    rows += [
        ("saturated", _percent("saturated_fraction")),
        ("overruns", lambda m: _num(m["overruns"])),
        ("feedback missing", lambda m: _num(m["feedback_missing"])),
        ("skipped samples", lambda m: _num(m["skipped_samples"])),
        ("dropped samples", lambda m: _num(m["dropped_samples"])),
        ("samples out of sequence", lambda m: _num(m.get("out_of_sequence_samples"))),
        ("log dropped records", lambda m: _num(m["log_dropped_records"])),
    ]
    for key, title in (
        ("latency_us", "latency"),
        ("period_jitter_us", "period jitter"),
        ("compute_us", "step"),
    ):
        for part in ("p50", "p99", "max"):
            rows.append((f"{title} {part} [us]", _dist(key, part)))
    rows += [
        ("bus load worst case", _bus("worst_case")),
        ("bus load nominal", _bus("nominal")),
        ("frames per period", _bus("frames_per_period")),
        ("truth samples", lambda m: _num(m["truth_samples"])),
    ]
    return rows


def format_table(metrics: list[dict[str, Any]], labels: list[str], output_unit: str = "") -> str:
    """The table, then the notes and warnings of each log (prefixed with its column title).
    ``output_unit`` labels the rows in the plant's output unit (``tracking error rms [rev]``)."""
    rows = _rows(metrics)
    if output_unit:
        rows = [(f"{n} [{output_unit}]" if n.startswith("tracking error") else n, g) for n, g in rows]
    cells = [[get(m) for m in metrics] for _, get in rows]
    first = max(len(name) for name, _ in rows)
    widths = [max(len(label), *(len(row[j]) for row in cells)) for j, label in enumerate(labels)]
    lines = ["  ".join([" " * first, *(label.rjust(w) for label, w in zip(labels, widths, strict=True))])]
    lines.append("  ".join(["-" * first, *("-" * w for w in widths)]))
    for (name, _), row in zip(rows, cells, strict=True):
        lines.append("  ".join([name.ljust(first), *(c.rjust(w) for c, w in zip(row, widths, strict=True))]))
    notes: dict[str, list[str]] = {}
    for label, m in zip(labels, metrics, strict=True):
        for note in m["notes"]:
            notes.setdefault(note, []).append(label)
    for note, which in notes.items():
        who = "all logs" if len(which) == len(labels) and len(labels) > 1 else ", ".join(which)
        lines.append(f"note ({who}): {note}")
    return "\n".join(lines)
