"""Plant physics: the continuous model ``x' = A x + B (u + w)``, ``y = C x``, integrated exactly.

Time is cut into sub-steps (cells) of ``h = Ts / substeps``, anchored at t = 0. Over a cell the
input is held, so the exact zero-order-hold solution is ``x+ = Phi_h x + Gam_h (u + w)`` with
``[[Phi_h, Gam_h], [0, 1]] = expm([[A, B], [0, 0]] h)``. The applied current ``u`` changes only
when the drive changes it (the caller splits time at those instants); the disturbance ``w`` is
held over each cell at its value at the cell's **midpoint** (second order accurate, and exact for
steps that start on a cell boundary). A current change inside a cell (real-time clock) splits the
cell at the change, resolved to ``SPLIT_RESOLUTION_NS``; the pieces' matrices are computed once
and cached.

The matrices are kept as Python floats: for the 2-state plant the cell update is hand-unrolled,
which is several times faster than numpy on 2x2 arrays. A 2-state plant also advances a whole
period (cells ``k * substeps`` to ``(k + 1) * substeps``, the lockstep drives' every step) in one
update, ``x+ = Phi_h^S x + (sum_i Phi_h^i Gam_h) u + d_k``: the same cells composed (the matrices
by the cell recurrence, in the same order every time), with ``d_k = sum_i Phi_h^(S-1-i) Gam_h
w_i`` over the period's disturbance cells, computed with numpy for a block of periods at once
(:func:`periods_per_block`). Every 2-state path (one period,
whole cells, cell pieces) takes whole periods this way, so all give the same bits; the result
differs from cell-by-cell updates by rounding only, while it is finite (a state or current that
overflows can end as a different mix of infinities and NaNs; the encoder faults in the same
period either way).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import scipy.linalg

from dob_hil.config import PlantConfig
from dob_hil.errors import ConfigError
from firmware_sim.disturbance import Disturbance

SPLIT_RESOLUTION_NS = 1000  # a current change inside a sub-step is placed to the nearest us
DISTURBANCE_BLOCK = 4096  # cell disturbance values computed together (vectorised), then cached
_NO_BLOCK = -(1 << 62)  # no block cached: no cell or period index falls inside it


def periods_per_block(substeps: int) -> int:
    """Periods whose disturbance terms d_k are computed together, then cached: as many as fit in
    ``DISTURBANCE_BLOCK`` cells (at least one), so a cache load costs what a cell block costs
    whatever the sub-steps (a real-time tick pays it between two deadlines)."""
    return max(1, DISTURBANCE_BLOCK // substeps)


_Matrices = tuple[list[list[float]], list[float]]


def check_single_axis(plant: PlantConfig) -> None:
    """The native protocol carries one current and one encoder: refuse anything else."""
    if plant.n_inputs != 1:
        raise ConfigError(
            "plant.B",
            f"firmware_sim simulates a single-axis drive (one current input); got {plant.n_inputs} inputs",
        )
    if plant.n_outputs != 1:
        raise ConfigError(
            "plant.C",
            f"firmware_sim simulates a single-axis drive (one encoder); got {plant.n_outputs} outputs",
        )


def zoh(
    A: npt.NDArray[np.float64], B: npt.NDArray[np.float64], h_s: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(Phi, Gam) of the exact zero-order-hold discretisation of ``(A, B)`` over ``h_s`` seconds."""
    n, m = A.shape[0], B.shape[1]
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A
    M[:n, n:] = B
    E = scipy.linalg.expm(M * h_s)
    return E[:n, :n].copy(), E[:n, n:].copy()


class PlantModel:
    """The true plant state of one axis, advanced between instants in integer nanoseconds."""

    def __init__(
        self,
        plant: PlantConfig,
        substeps: int,
        disturbance: Disturbance,
        initial_state: Sequence[float] | None = None,
    ) -> None:
        self._check_plant(plant)
        if substeps < 1:
            raise ConfigError("sim.substeps", f"must be >= 1, got {substeps}")
        self.n_states = plant.n_states
        self.period_ns = plant.period_ns
        self.substeps = substeps
        self.cell_ns = plant.period_ns / substeps  # may be fractional
        self.cell_s = self.cell_ns * 1e-9
        self._A = np.asarray(plant.A, dtype=np.float64)
        self._B = np.asarray(plant.B, dtype=np.float64)
        self._c = [float(v) for v in plant.C[0]]
        # the output row of a 2-state plant, for the fused periods' inline position()
        self.c_2state: tuple[float, float] | None = (self._c[0], self._c[1]) if self.n_states == 2 else None
        self._disturbance = disturbance
        self._full = self._matrices(self.cell_s)
        phi, gam = self._full
        self._m2 = (
            (phi[0][0], phi[0][1], phi[1][0], phi[1][1], gam[0], gam[1]) if self.n_states == 2 else None
        )
        self._p2 = _compose_period(self._m2, substeps) if self._m2 is not None else None
        self._period_block = periods_per_block(substeps)
        self._d_w: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None = None
        self._d_first = _NO_BLOCK  # the first period of the cached block
        self._d0: list[float] = []  # d_k of the cached block of periods, per state
        self._d1: list[float] = []
        self._split_max = max(1, round(self.cell_ns / SPLIT_RESOLUTION_NS))
        self._w_block_index = _NO_BLOCK
        self._w_block: list[float] = []
        self._head_cache: dict[int, _Matrices] = {}
        self._tail_cache: dict[int, _Matrices] = {}
        if initial_state is None:
            self._x = [0.0] * self.n_states
        else:
            if len(initial_state) != self.n_states:
                raise ConfigError(
                    "sim.initial_state", f"expected {self.n_states} values, got {len(initial_state)}"
                )
            self._x = [float(v) for v in initial_state]

    @staticmethod
    def _check_plant(plant: PlantConfig) -> None:
        """The plants this model integrates (one input here; see firmware_sim.axes.plant)."""
        check_single_axis(plant)

    # --- read-out ------------------------------------------------------------------------------
    @property
    def state(self) -> tuple[float, ...]:
        return tuple(self._x)

    def position(self) -> float:
        """The first output, ``C[0] @ x``, in the plant's output unit."""
        x, c = self._x, self._c
        if self.n_states == 2:
            return c[0] * x[0] + c[1] * x[1]
        return math.fsum(ci * xi for ci, xi in zip(c, x, strict=True))

    # --- integration ---------------------------------------------------------------------------
    def advance(self, t0_ns: int, t1_ns: int, current_A: float) -> None:
        """Integrate from ``t0_ns`` to ``t1_ns`` with ``current_A`` held (plus the disturbance)."""
        if t1_ns <= t0_ns:
            return
        S, P = self.substeps, self.period_ns
        j0, r0 = divmod(t0_ns * S, P)
        j1, r1 = divmod(t1_ns * S, P)
        if r0 == 0 and r1 == 0:  # both ends on cell boundaries (always, in lockstep)
            self._cells(j0, j1, current_A)
            return
        k0 = self._split_index(r0)
        k1 = self._split_index(r1)
        if k0 == self._split_max:
            j0, k0 = j0 + 1, 0
        if k1 == self._split_max:
            j1, k1 = j1 + 1, 0
        if j0 == j1:  # both ends inside one cell
            if k1 > k0:
                self._step(self._head(k1 - k0), current_A + self._w(j0))
            return
        if k0 > 0:  # the rest of the first cell
            self._step(self._tail(k0), current_A + self._w(j0))
            j0 += 1
        if j1 > j0:
            self._cells(j0, j1, current_A)
        if k1 > 0:  # the start of the last cell
            self._step(self._head(k1), current_A + self._w(j1))

    def advance_2state(self, t0_ns: int, t1_ns: int, current_A: float) -> bool:
        """:meth:`advance` (``t0_ns`` to ``t1_ns``, ``current_A`` held), bit for bit, where it
        takes the unrolled 2-state path in one call: a 2-state plant and both ends on cell
        boundaries (always so for a lockstep period). Otherwise False with nothing changed, and the
        caller takes :meth:`advance`.

        The per-period hot path of the lockstep drives (native, CiA 402 and ODrive): one whole
        period is one composed update (module docstring). As :meth:`advance`, an arithmetic error
        in the update (overflow) propagates with the state unchanged."""
        p2 = self._p2
        P = self.period_ns
        if p2 is None:  # not a single-input 2-state plant (no _m2 either)
            return False
        if t1_ns - t0_ns != P or t0_ns % P:  # not one whole period: whole cells, if on the grid
            S = self.substeps
            j0, r0 = divmod(t0_ns * S, P)
            j1, r1 = divmod(t1_ns * S, P)
            if r0 or r1:
                return False
            self._cells_2state(j0, j1, current_A)
            return True
        a00, a01, a10, a11, b0, b1 = p2
        x0, x1 = self._x
        u = current_A
        if self._disturbance.is_zero:
            self._x = [a00 * x0 + a01 * x1 + b0 * u, a10 * x0 + a11 * x1 + b1 * u]
            return True
        k = t0_ns // P - self._d_first
        if not 0 <= k < self._period_block:
            k = self._load_d_block(t0_ns // P)
        self._x = [a00 * x0 + a01 * x1 + b0 * u + self._d0[k], a10 * x0 + a11 * x1 + b1 * u + self._d1[k]]
        return True

    def _cells_2state(self, j0: int, j1: int, u: float) -> None:
        """Cells j0 .. j1-1 of the 2-state plant: cell by cell up to the first period boundary,
        whole periods composed, cell by cell after the last one (same arithmetic as
        :meth:`advance_2state`'s one period)."""
        p2 = self._p2
        assert p2 is not None
        S = self.substeps
        first_k = -(-j0 // S)  # the first whole period
        last_k = j1 // S
        if first_k >= last_k:  # no whole period inside
            self._cell_steps(j0, j1, u)
            return
        self._cell_steps(j0, first_k * S, u)
        a00, a01, a10, a11, b0, b1 = p2
        x0, x1 = self._x
        if self._disturbance.is_zero:
            for _ in range(first_k, last_k):
                x0, x1 = a00 * x0 + a01 * x1 + b0 * u, a10 * x0 + a11 * x1 + b1 * u
        else:
            block = self._period_block
            for k in range(first_k, last_k):
                o = k - self._d_first
                if not 0 <= o < block:
                    o = self._load_d_block(k)
                x0, x1 = (
                    a00 * x0 + a01 * x1 + b0 * u + self._d0[o],
                    a10 * x0 + a11 * x1 + b1 * u + self._d1[o],
                )
        self._x = [x0, x1]
        self._cell_steps(last_k * S, j1, u)

    def _cell_steps(self, j0: int, j1: int, u: float) -> None:
        """Cells j0 .. j1-1 of the 2-state plant one by one."""
        if j1 <= j0:
            return
        m2 = self._m2
        assert m2 is not None
        p00, p01, p10, p11, g0, g1 = m2
        x0, x1 = self._x
        if self._disturbance.is_zero:
            for _ in range(j0, j1):
                x0, x1 = p00 * x0 + p01 * x1 + g0 * u, p10 * x0 + p11 * x1 + g1 * u
        else:
            for w in self._w_cells(j0, j1):
                v = u + w
                x0, x1 = p00 * x0 + p01 * x1 + g0 * v, p10 * x0 + p11 * x1 + g1 * v
        self._x = [x0, x1]

    def _load_d_block(self, period: int) -> int:
        """Cache d_k of the block of periods holding ``period``; returns its offset in the block.
        d_k: the period's disturbance cells (midpoint values, as :meth:`_w`) weighted by
        ``Phi_h^(S-1-i) Gam_h``, the cell recurrence's effect of cell i at the period's end."""
        n, S = self._period_block, self.substeps
        block_first = period // n * n
        first = block_first * S
        t_s = (np.arange(first, first + n * S, dtype=np.float64) + 0.5) * self.cell_s
        w = self._disturbance.values_A(t_s).reshape(n, S)
        m0, m1 = self._d_weights()
        self._d0, self._d1 = (w * m0).sum(axis=1).tolist(), (w * m1).sum(axis=1).tolist()
        self._d_first = block_first
        return period - block_first

    def _d_weights(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Per state, ``Phi_h^(S-1-i) Gam_h`` for the cells i of a period (computed once)."""
        if self._d_w is None:
            m2 = self._m2
            assert m2 is not None
            p00, p01, p10, p11, g0, g1 = m2
            S = self.substeps
            m0, m1 = np.empty(S), np.empty(S)
            v0, v1 = g0, g1  # the last cell: Gam_h; each earlier one: Phi_h times the next
            for i in range(S - 1, -1, -1):
                m0[i], m1[i] = v0, v1
                v0, v1 = p00 * v0 + p01 * v1, p10 * v0 + p11 * v1
            self._d_w = (m0, m1)
        return self._d_w

    def disturbance_changed(self) -> None:
        """The disturbance's origin moved: drop the cached per-cell and per-period values."""
        self._w_block_index = _NO_BLOCK
        self._w_block = []
        self._d_first = _NO_BLOCK
        self._d0, self._d1 = [], []

    def _split_index(self, remainder: int) -> int:
        # remainder / substeps ns into the cell, in units of SPLIT_RESOLUTION_NS
        if remainder == 0:
            return 0
        k = round(remainder / (self.substeps * SPLIT_RESOLUTION_NS))
        return min(k, self._split_max)

    # --- disturbance per cell (midpoint value), cached in vectorised blocks ----------------------
    def _w(self, cell: int) -> float:
        if self._disturbance.is_zero:
            return 0.0
        block, offset = divmod(cell, DISTURBANCE_BLOCK)
        if block != self._w_block_index:
            self._load_w_block(block)
        return self._w_block[offset]

    def _w_cells(self, j0: int, j1: int) -> list[float]:
        """Disturbance of cells j0 .. j1-1."""
        b0, o0 = divmod(j0, DISTURBANCE_BLOCK)
        b1, o1 = divmod(j1, DISTURBANCE_BLOCK)
        if b0 != self._w_block_index:
            self._load_w_block(b0)
        if b1 == b0 or (b1 == b0 + 1 and o1 == 0):
            return self._w_block[o0 : o1 if b1 == b0 else DISTURBANCE_BLOCK]
        return [self._w(j) for j in range(j0, j1)]

    def _load_w_block(self, block: int) -> None:
        first = block * DISTURBANCE_BLOCK
        t_s = (np.arange(first, first + DISTURBANCE_BLOCK, dtype=np.float64) + 0.5) * self.cell_s
        self._w_block = self._disturbance.values_A(t_s).tolist()
        self._w_block_index = block

    def _cells(self, j0: int, j1: int, u: float) -> None:
        """Whole cells j0 .. j1-1 with the full sub-step matrices (the hot path)."""
        if self._m2 is not None:
            self._cells_2state(j0, j1, u)
            return
        if self._disturbance.is_zero:
            for _ in range(j0, j1):
                self._step(self._full, u)
        else:
            for w in self._w_cells(j0, j1):
                self._step(self._full, u + w)

    def _step(self, mats: _Matrices, v: float) -> None:
        phi, gam = mats
        x = self._x
        self._x = [
            math.fsum(p * xi for p, xi in zip(row, x, strict=True)) + g * v
            for row, g in zip(phi, gam, strict=True)
        ]

    # --- matrices ------------------------------------------------------------------------------
    def _matrices(self, h_s: float) -> _Matrices:
        Phi, Gam = zoh(self._A, self._B, h_s)
        return [[float(v) for v in row] for row in Phi], [float(v) for v in Gam[:, 0]]

    def _head(self, k: int) -> _Matrices:
        """The first ``k`` resolution units of a cell."""
        m = self._head_cache.get(k)
        if m is None:
            m = self._head_cache[k] = self._matrices(k * SPLIT_RESOLUTION_NS * 1e-9)
        return m

    def _tail(self, k: int) -> _Matrices:
        """A cell from ``k`` resolution units to its end."""
        m = self._tail_cache.get(k)
        if m is None:
            m = self._tail_cache[k] = self._matrices((self.cell_ns - k * SPLIT_RESOLUTION_NS) * 1e-9)
        return m


def _compose_period(
    m2: tuple[float, float, float, float, float, float], substeps: int
) -> tuple[float, float, float, float, float, float]:
    """(Phi_h^S, sum_i Phi_h^i Gam_h) of a 2-state plant, unrolled as ``m2``: the cell recurrence
    run ``substeps`` times on the identity and on a zero input vector with unit input."""
    p00, p01, p10, p11, g0, g1 = m2
    a00, a01, a10, a11 = 1.0, 0.0, 0.0, 1.0
    b0 = b1 = 0.0
    for _ in range(substeps):
        a00, a01, a10, a11 = (
            p00 * a00 + p01 * a10,
            p00 * a01 + p01 * a11,
            p10 * a00 + p11 * a10,
            p10 * a01 + p11 * a11,
        )
        b0, b1 = p00 * b0 + p01 * b1 + g0, p10 * b0 + p11 * b1 + g1
    return a00, a01, a10, a11, b0, b1
