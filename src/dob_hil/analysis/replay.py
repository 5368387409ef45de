"""``replay --verify`` and ``replay --design``: the controller re-run over a log (:mod:`rerun`).

:func:`verify` re-runs the logged design with the logged DOB setting, the logged drive's
quantizer and missing-feedback policy, and compares every logged field the controller produced
bit for bit (float64 compared as bit patterns, so -0.0 != 0.0 and NaN == NaN of the same bits):
``position`` (the estimator's input, which differs from the measurement only when feedback was
missing), ``x_hat``, ``x_bar``, ``u_fb``, ``u_dist``, ``u_cmd_a``, ``u_applied_a``, ``dac_counts``
and the saturation flag; with the config at hand, also ``x_ref`` against the reference generator.

:func:`redesign` runs another design open loop on the same recorded measurements and references
(same DOB setting, same drive quantizer) and compares what it would have commanded with what
was sent.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.analysis.loaded import LoadedLog
from dob_hil.analysis.rerun import MissingPolicy, Quantize, Rerun, RerunChain
from dob_hil.config import Config, DriveConfig
from dob_hil.control.step import compile_step
from dob_hil.design import Design
from dob_hil.design.tracking import controller_gains, tracking_map
from dob_hil.errors import DesignError, DobHilError
from dob_hil.link.native import DacQuantizer
from dob_hil.log.schemas import FLAG_SATURATED
from dob_hil.profiles import get_profile

MAX_REPORTED = 10
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Mismatch:
    seq: int
    field: str
    logged: str
    replayed: str


@dataclass
class VerifyResult:
    samples: int
    dob_enabled: bool
    fields: list[str]
    identical: bool
    mismatched_samples: int
    mismatches_by_field: dict[str, int]
    first_mismatches: list[Mismatch]
    first_mismatch_seq: int | None
    resyncs: list[int]
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _require_design(log: LoadedLog) -> Design:
    if log.design is None:
        raise DobHilError(f"{log.path}: the log has no usable design.json attachment; cannot re-run it")
    return log.design


def logged_drive(log: LoadedLog, notes: list[str]) -> DriveConfig:
    """The drive settings the run used: its config, else the run metadata's limit and LSB."""
    if log.config is not None:
        return log.config.drive
    try:
        drive = DriveConfig(
            current_limit_A=float(log.run["current_limit_A"]), dac_lsb_A=float(log.run["dac_lsb_A"])
        )
    except (KeyError, ValueError) as exc:
        raise DobHilError(
            f"{log.path}: neither a config.toml attachment nor current_limit_A/dac_lsb_A in the run "
            f"metadata ({exc}); the quantizer cannot be reproduced"
        ) from None
    notes.append("no config attachment: quantizer from the run metadata's current_limit_A and dac_lsb_A")
    return drive


def logged_missing_policy(log: LoadedLog, notes: list[str]) -> MissingPolicy:
    if log.config is not None:
        return MissingPolicy(log.config.run.missing_feedback_policy, log.config.run.max_missing_periods)
    policy = log.run.get("missing_feedback_policy", "hold")
    notes.append(f"no config attachment: missing-feedback policy {policy!r}, max_missing_periods 3 assumed")
    return MissingPolicy(policy, 3)


def per_axis(quantize: Quantize, n_inputs: int) -> Quantize:
    """The drive's quantizer applied to each axis's current on its own (every axis of a
    multi-axis run is one drive with the same limit and DAC step): ``quantize`` itself for one
    input; saturated when any axis saturated."""
    if n_inputs == 1:
        return quantize

    def each(current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        axes = [quantize((u,)) for u in current_A]
        return (
            tuple(codes[0] for codes, _, _ in axes),
            tuple(applied[0] for _, applied, _ in axes),
            any(saturated for _, _, saturated in axes),
        )

    return each


def _chain(log: LoadedLog, design: Design, drive: DriveConfig, missing: MissingPolicy) -> RerunChain:
    step = compile_step(controller_gains(design), log.dob_enabled)  # with the reference feedforward
    make_quantizer = get_profile(drive.profile).make_quantizer
    quantize = DacQuantizer(drive).quantize if make_quantizer is None else make_quantizer(drive)
    return RerunChain(step, per_axis(quantize, step.n_inputs), design.C, missing, log.data.events)


def _rerun_with(log: LoadedLog, design: Design, drive: DriveConfig, missing: MissingPolicy) -> Rerun:
    return _chain(log, design, drive, missing).feed(log.data.samples)


def _bits(values: npt.NDArray[Any]) -> npt.NDArray[Any]:
    a = np.ascontiguousarray(values)
    if a.dtype == np.float64:
        return a.view(np.uint64)
    return a.astype(np.int64)


def _reference(log: LoadedLog, config: Config, design: Design) -> npt.NDArray[np.float64] | None:
    from dob_hil.control.reference import make_reference

    n_states = log.data.layout.n_states
    try:
        t = tracking_map(design)
        ref = make_reference(config.reference, n_states, config.plant.period_s, state_map=(t.Nx, t.Nv))
    except DobHilError:
        return None
    seqs = log.data.samples["seq"].tolist()
    return np.asarray([ref.at(k) for k in seqs], dtype=np.float64).reshape(len(seqs), n_states)


def verify(log: LoadedLog, *, max_reported: int = MAX_REPORTED) -> VerifyResult:
    """Re-run the logged controller and compare bit for bit (module docstring)."""
    design = _require_design(log)
    notes: list[str] = []
    drive = logged_drive(log, notes)
    missing = logged_missing_policy(log, notes)
    s = log.data.samples
    r = _rerun_with(log, design, drive, missing)
    pairs: list[tuple[str, npt.NDArray[Any], npt.NDArray[Any]]] = [
        ("position", s["position"], r.position),
        ("x_hat", s["x_hat"], r.x_hat),
        ("x_bar", s["x_bar"], r.x_bar),
        ("u_fb", s["u_fb"], r.u_fb),
        ("u_dist", s["u_dist"], r.u_dist),
        ("u_cmd_a", s["u_cmd_a"], r.u_cmd),
        ("u_applied_a", s["u_applied_a"], r.u_applied),
        ("dac_counts", s["dac_counts"], r.dac_counts),
        ("saturated", (s["flags"] & FLAG_SATURATED) != 0, r.saturated),
    ]
    if log.config is not None:
        x_ref = _reference(log, log.config, design)
        if x_ref is None:
            notes.append("the reference could not be rebuilt from the config; x_ref not checked")
        else:
            pairs.append(("x_ref", s["x_ref"], x_ref))
    n = len(s)
    any_bad = np.zeros(n, dtype=bool)
    by_field: dict[str, int] = {}
    first: list[Mismatch] = []
    seqs = s["seq"]
    for name, logged, replayed in pairs:
        lb, rb = _bits(logged), _bits(replayed)
        bad = (lb != rb).reshape(n, -1).any(axis=1)
        count = int(np.count_nonzero(bad))
        by_field[name] = count
        any_bad |= bad
        for i in np.flatnonzero(bad)[:max_reported].tolist():
            first.append(
                Mismatch(
                    int(seqs[i]),
                    name,
                    repr(np.asarray(logged[i]).tolist()),
                    repr(np.asarray(replayed[i]).tolist()),
                )
            )
    first.sort(key=lambda mm: mm.seq)
    bad_rows = np.flatnonzero(any_bad)
    if r.resyncs:
        notes.append(f"{len(r.resyncs)} unexplained sequence gap(s): re-started from the logged x_bar there")
    return VerifyResult(
        samples=n,
        dob_enabled=log.dob_enabled,
        fields=[name for name, _, _ in pairs],
        identical=len(bad_rows) == 0 and n > 0,
        mismatched_samples=len(bad_rows),
        mismatches_by_field=by_field,
        first_mismatches=first[:max_reported],
        first_mismatch_seq=int(seqs[bad_rows[0]]) if len(bad_rows) else None,
        resyncs=r.resyncs,
        notes=notes,
    )


@dataclass(frozen=True)
class RedesignSeries:
    """What the redesign plot draws, decimated as it was computed (min/max per bucket of every
    drawn signal, :mod:`dob_hil.analysis.downsample`): at most a few thousand rows per input,
    whatever the log's length."""

    t_s: FloatArray  # from the first sample
    sent_A: FloatArray  # (rows, inputs)
    other_A: FloatArray


@dataclass
class RedesignResult:
    design_name: str
    samples: int
    dob_enabled: bool
    u_applied_diff_rms_A: float
    u_applied_diff_max_A: float
    u_cmd_diff_rms_A: float
    u_cmd_diff_max_A: float
    sent_rms_A: float
    other_rms_A: float
    other_saturated_fraction: float
    notes: list[str] = field(default_factory=list)
    # per plant input (one entry for a single-input plant): the same figures axis by axis
    u_applied_diff_rms_A_per_input: list[float] = field(default_factory=list)
    u_applied_diff_max_A_per_input: list[float] = field(default_factory=list)
    sent_rms_A_per_input: list[float] = field(default_factory=list)
    other_rms_A_per_input: list[float] = field(default_factory=list)
    rerun: Rerun | None = None  # the other design's commands, when kept (not in to_dict)
    series: RedesignSeries | None = None  # for the plot (not in to_dict)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("rerun")
        d.pop("series")
        return d


def check_compatible(log: LoadedLog, other: Design) -> None:
    """DesignError unless ``other`` has the log's period and dimensions."""
    layout = log.data.layout
    if other.period_ns != log.period_ns:
        raise DesignError(
            f"design {other.name!r}: period {other.period_ns} ns differs from the log's {log.period_ns} ns"
        )
    have = (other.n_states, other.n_inputs, other.n_outputs)
    want = (layout.n_states, layout.n_inputs, layout.n_outputs)
    if have != want:
        raise DesignError(
            f"design {other.name!r}: states/inputs/outputs {have} differ from the log's {want} "
            "(an input delay changes the state count)"
        )


class _Sums:
    """Sums of squares and maxima per input, accumulated block by block."""

    def __init__(self, m: int) -> None:
        self.sq = np.zeros(m)
        self.max = np.zeros(m)

    def add(self, x: FloatArray) -> None:
        if len(x):
            self.sq += np.sum(np.square(x), axis=0)
            self.max = np.maximum(self.max, np.max(np.abs(x), axis=0))

    def rms(self, n: int) -> list[float]:
        return [float(np.sqrt(v / n)) if n else 0.0 for v in self.sq]

    def rms_all(self, n: int) -> float:
        return float(np.sqrt(np.sum(self.sq) / (n * len(self.sq)))) if n else 0.0

    def max_all(self) -> float:
        return float(np.max(self.max)) if len(self.max) else 0.0


def _decimated_rows(t: FloatArray, columns: list[FloatArray], max_points: int) -> npt.NDArray[np.int64]:
    """Rows that keep every column's min/max envelope (:func:`envelope_indices`)."""
    from dob_hil.analysis.downsample import envelope_indices

    picks = [envelope_indices(c, max_points) for c in columns]
    return np.unique(np.concatenate(picks)) if picks else np.arange(len(t), dtype=np.int64)


def redesign(log: LoadedLog, other: Design) -> RedesignResult:
    """What ``other`` would have commanded on the log's measurements (module docstring), over the
    samples ``log`` holds; the result keeps the whole re-run (``rerun``)."""
    return redesign_blocks(log, [log.data.samples], other, keep_rerun=True)


def redesign_blocks(
    log: LoadedLog,
    blocks: Iterable[npt.NDArray[np.void]],
    other: Design,
    *,
    total_samples: int | None = None,
    keep_rerun: bool = False,
) -> RedesignResult:
    """:func:`redesign` over the samples given block by block (a streamed log): memory bounded by
    a block and the plot's decimated series (``total_samples``, the expected count, spreads the
    plot's points over the blocks), unless ``keep_rerun``."""
    from dob_hil.analysis.downsample import DEFAULT_MAX_POINTS

    check_compatible(log, other)
    notes: list[str] = []
    drive = logged_drive(log, notes)
    missing = logged_missing_policy(log, notes)
    chain = _chain(log, other, drive, missing)
    m = chain.step.n_inputs
    diff_sums, cmd_sums, sent_sums, other_sums = _Sums(m), _Sums(m), _Sums(m), _Sums(m)
    n = saturated = 0
    t0_ns: int | None = None
    kept: list[tuple[FloatArray, FloatArray, FloatArray]] = []
    reruns: list[Rerun] = []
    for block in blocks:
        if len(block) == 0:
            continue
        r = chain.feed(block)
        sent = np.asarray(block["u_applied_a"], dtype=np.float64).reshape(len(block), m)
        cmd = np.asarray(block["u_cmd_a"], dtype=np.float64).reshape(len(block), m)
        diff = r.u_applied - sent
        diff_sums.add(diff)
        cmd_sums.add(r.u_cmd - cmd)
        sent_sums.add(sent)
        other_sums.add(r.u_applied)
        saturated += int(np.count_nonzero(r.saturated))
        n += len(block)
        t_ns = block["time_ns"].astype(np.int64)
        if t0_ns is None:
            t0_ns = int(t_ns[0])
        t = np.asarray((t_ns - t0_ns) * 1e-9, dtype=np.float64)
        budget = DEFAULT_MAX_POINTS
        if total_samples:
            budget = max(16, -(-DEFAULT_MAX_POINTS * len(block) // total_samples))
        rows = _decimated_rows(t, [c[:, j] for c in (sent, r.u_applied, diff) for j in range(m)], budget)
        kept.append((t[rows], sent[rows], r.u_applied[rows]))
        if keep_rerun:
            reruns.append(r)
    notes.append("open loop: the plant's response to the other commands is not modelled")
    series = RedesignSeries(
        np.concatenate([k[0] for k in kept]) if kept else np.zeros(0),
        np.concatenate([k[1] for k in kept]) if kept else np.zeros((0, m)),
        np.concatenate([k[2] for k in kept]) if kept else np.zeros((0, m)),
    )
    return RedesignResult(
        design_name=other.name,
        samples=n,
        dob_enabled=log.dob_enabled,
        u_applied_diff_rms_A=diff_sums.rms_all(n),
        u_applied_diff_max_A=diff_sums.max_all(),
        u_cmd_diff_rms_A=cmd_sums.rms_all(n),
        u_cmd_diff_max_A=cmd_sums.max_all(),
        sent_rms_A=sent_sums.rms_all(n),
        other_rms_A=other_sums.rms_all(n),
        other_saturated_fraction=saturated / n if n else 0.0,
        notes=notes,
        u_applied_diff_rms_A_per_input=diff_sums.rms(n),
        u_applied_diff_max_A_per_input=[float(v) for v in diff_sums.max],
        sent_rms_A_per_input=sent_sums.rms(n),
        other_rms_A_per_input=other_sums.rms(n),
        rerun=_joined(reruns) if keep_rerun else None,
        series=series,
    )


def _joined(parts: list[Rerun]) -> Rerun | None:
    if len(parts) <= 1:
        return parts[0] if parts else None

    def cat(name: str) -> Any:
        return np.concatenate([getattr(p, name) for p in parts])

    return Rerun(
        position=cat("position"),
        x_hat=cat("x_hat"),
        x_bar=cat("x_bar"),
        u_fb=cat("u_fb"),
        u_dist=cat("u_dist"),
        u_cmd=cat("u_cmd"),
        u_applied=cat("u_applied"),
        dac_counts=cat("dac_counts"),
        saturated=cat("saturated"),
        resyncs=[seq for p in parts for seq in p.resyncs],
    )
