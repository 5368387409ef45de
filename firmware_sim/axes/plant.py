"""The coupled plant of a multi-axis drive: ``x' = A x + B (u + w)`` with N currents in, N outputs.

:class:`CoupledPlantModel` is :class:`firmware_sim.plant.PlantModel` (the same cells, splits,
midpoint disturbance and caches) with a current *vector* ``u`` (one per axis) and a disturbance
vector ``w`` (each ``[[sim.disturbance]]`` on its ``input_index``), in numpy. Axis i reads output
i, ``C[i] @ x``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import numpy as np
import numpy.typing as npt
import scipy.linalg

from dob_hil.config import PlantConfig
from dob_hil.link.axes import check_square
from firmware_sim.disturbance import Disturbance
from firmware_sim.plant import DISTURBANCE_BLOCK, SPLIT_RESOLUTION_NS, PlantModel, zoh

Vector = npt.NDArray[np.float64]


class InputDisturbances:
    """One :class:`Disturbance` per plant input, read together as a vector per instant."""

    def __init__(self, per_input: Sequence[Disturbance]) -> None:
        self.per_input = tuple(per_input)

    @property
    def is_zero(self) -> bool:
        return all(d.is_zero or d.origin_s is None for d in self.per_input)

    def values_A(self, t_s: Vector) -> npt.NDArray[np.float64]:
        """Shape ``(len(t_s), n_inputs)``."""
        return np.stack([d.values_A(t_s) for d in self.per_input], axis=1)

    def value_A(self, t_s: float) -> tuple[float, ...]:
        return tuple(d.value_A(t_s) for d in self.per_input)


class CoupledPlantModel(PlantModel):
    """The true state of a square multi-input plant (module docstring)."""

    def __init__(
        self,
        plant: PlantConfig,
        substeps: int,
        disturbances: InputDisturbances,
        initial_state: Sequence[float] | None = None,
    ) -> None:
        self.n_inputs = plant.n_inputs
        self._C = np.asarray(plant.C, dtype=np.float64)
        self.inputs = disturbances
        super().__init__(plant, substeps, cast(Disturbance, disturbances), initial_state)
        self._m2 = None  # the unrolled 2-state path is single-input
        self._p2 = None  # (and so is its whole-period update)
        self._xv: Vector = np.asarray(self._x, dtype=np.float64)
        phi = cast(tuple[Vector, Vector], self._full)[0]
        powers = [np.eye(self.n_states)]
        for _ in range(substeps):
            powers.append(phi @ powers[-1])
        self._powers = np.stack(powers)

    def precompute_splits(self) -> None:
        """Compute every cell piece a current change inside a cell can need, so that a real-time
        clock never computes a matrix exponential between two deadlines: one exponential of
        ``SPLIT_RESOLUTION_NS`` and its powers (``E(k h) = E(h)^k`` for the augmented ``[[A, B],
        [0, 0]]``), the cell's tails from the heads when the cell is a whole number of them."""
        n, m = self.n_states, self.n_inputs
        aug = np.zeros((n + m, n + m))
        aug[:n, :n] = self._A
        aug[:n, n:] = self._B
        step = scipy.linalg.expm(aug * (SPLIT_RESOLUTION_NS * 1e-9))
        power = np.eye(n + m)
        heads: dict[int, tuple[Vector, Vector]] = {}
        for k in range(1, self._split_max + 1):
            power = power @ step
            heads[k] = (power[:n, :n].copy(), power[:n, n:].copy())
        for k, mats in heads.items():
            self._head_cache.setdefault(k, cast(tuple[list[list[float]], list[float]], mats))
        if self.cell_ns == self._split_max * SPLIT_RESOLUTION_NS:  # tail(k) = head(cell - k)
            for k in range(1, self._split_max):
                mats = heads[self._split_max - k]
                self._tail_cache.setdefault(k, cast(tuple[list[list[float]], list[float]], mats))

    def finite(self) -> bool:
        """Every state is a finite number (the physics did not overflow)."""
        return bool(np.all(np.isfinite(self._xv)) and np.all(np.abs(self._xv) < 1e300))

    @staticmethod
    def _check_plant(plant: PlantConfig) -> None:
        check_square(plant)

    # --- read-out ------------------------------------------------------------------------------
    @property
    def state(self) -> tuple[float, ...]:
        return tuple(self._xv.tolist())

    def output(self, axis: int) -> float:
        """Output ``axis``, ``C[axis] @ x``, in the plant's output unit."""
        return float(self._C[axis] @ self._xv)

    def position(self) -> float:
        return self.output(0)

    # --- integration ---------------------------------------------------------------------------
    def advance_vector(self, t0_ns: int, t1_ns: int, currents_A: Sequence[float]) -> None:
        """Integrate from ``t0_ns`` to ``t1_ns`` with one held current per axis (plus disturbances)."""
        self.advance(t0_ns, t1_ns, cast(float, np.asarray(currents_A, dtype=np.float64)))

    def _load_w_block(self, block: int) -> None:
        first = block * DISTURBANCE_BLOCK
        t_s = (np.arange(first, first + DISTURBANCE_BLOCK, dtype=np.float64) + 0.5) * self.cell_s
        self._w_block = cast(list[float], self.inputs.values_A(t_s))
        self._w_block_index = block

    def _cells(self, j0: int, j1: int, u: float) -> None:
        """Cells j0 .. j1-1: ``x_L = Phi^L x_0 + sum_j Phi^(L-1-j) Gam v_j`` in one product for up
        to one period of cells (the powers of Phi are computed once), cell by cell beyond."""
        n_cells = j1 - j0
        if n_cells <= 0:
            return
        phi, gam = cast(tuple[Vector, Vector], self._full)
        u_vec = np.asarray(u, dtype=np.float64)
        if self.inputs.is_zero:
            drives = np.broadcast_to(gam @ u_vec, (n_cells, self.n_states))
        else:
            drives = (np.asarray(self._w_cells(j0, j1), dtype=np.float64) + u_vec) @ gam.T
        if n_cells <= self.substeps:
            powers = self._powers  # powers[k] = Phi^k, k = 0 .. substeps
            self._xv = powers[n_cells] @ self._xv + np.einsum("jab,jb->a", powers[n_cells - 1 :: -1], drives)
            return
        x = self._xv
        for d in drives:
            x = phi @ x + d
        self._xv = x

    def _step(self, mats: object, v: float) -> None:
        phi, gam = cast(tuple[Vector, Vector], mats)
        self._xv = phi @ self._xv + gam @ np.asarray(v, dtype=np.float64)

    def _matrices(self, h_s: float) -> tuple[list[list[float]], list[float]]:
        Phi, Gam = zoh(self._A, self._B, h_s)
        return cast(tuple[list[list[float]], list[float]], (Phi, Gam))
