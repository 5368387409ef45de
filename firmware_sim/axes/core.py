"""The firmware of N drive nodes on one bus sharing one coupled plant, independent of any clock.

Axis i is node ``node_ids[i]`` (:func:`dob_hil.link.axes.axis_node_ids`), plant input i (its
current) and plant output i (its encoder). Each axis is a :class:`firmware_sim.core.DriveCore`
(its own state machine, watchdog, DAC, quantized encoder, current path, command acceptance and
frames: everything ``docs/PROTOCOL.md`` says of one node) whose plant is a view of output i of the
one :class:`~firmware_sim.axes.plant.CoupledPlantModel`. This core integrates that plant with every
axis's current, and ticks every axis on one clock: at a sample instant all axes close the period
and latch their encoders (all FEEDBACKs of the period), and commands received act at their
instant, each on its own input.

Differences from one drive, all of them about the shared plant and clock:

* Disturbances (``[[sim.disturbance]]``) act on their ``input_index``; they start at the first
  enable of any axis (one origin for all).
* ``[sim.faults]`` is injected on axis 0 (the first node); ``silent_at_s`` silences every node
  (the clock's one transmitter).
* A plant the physics cannot integrate faults every axis (ENCODER).
* The sequence numbers of all axes count the same samples; the drive refuses the
  ``restart_sequence_on_enable`` variant (axes enabled at different samples would disagree).
"""

from __future__ import annotations

from dataclasses import replace
from typing import cast

from dob_hil.config import Config, FaultsConfig
from dob_hil.link.axes import axis_node_ids, check_square
from dob_hil.link.protocol import DriveState, FaultCode, FrameKind
from firmware_sim.axes.plant import CoupledPlantModel, InputDisturbances
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.core import DriveCore, DriveStats, FrameResult
from firmware_sim.disturbance import Disturbance
from firmware_sim.plant import PlantModel
from firmware_sim.truth import AxesTruth

OutgoingId = tuple[int, bytes]  # (arbitration id, payload)

__all__ = ["AxesTruth", "MultiAxisCore", "axis_config"]


class _AxisOutput:
    """What an axis's DriveCore sees of the plant: output ``axis`` of the coupled plant."""

    def __init__(self, owner: MultiAxisCore, axis: int) -> None:
        self._owner = owner
        self._axis = axis

    @property
    def state(self) -> tuple[float, ...]:
        return self._owner.plant.state

    def position(self) -> float:
        return self._owner.plant.output(self._axis)

    def disturbance_changed(self) -> None:
        """The axis's first enable set its disturbance origin: every input starts then."""
        self._owner.start_disturbances(self._axis)


def axis_config(config: Config, axis: int, node_id: int) -> Config:
    """The config of ``axis``'s firmware: its own node, encoder noise seed ``seed + axis``, and
    ``[sim.faults]`` on axis 0 only (its plant and disturbance are the multi-axis core's)."""
    sim = config.sim
    drive = replace(config.drive, node_id=node_id, node_ids=None)
    faults = sim.faults if axis == 0 else FaultsConfig()
    sim_axis = replace(sim, disturbances=(), faults=faults, seed=sim.seed + axis)
    return replace(config, drive=drive, sim=sim_axis)


class MultiAxisCore:
    def __init__(
        self,
        config: Config,
        *,
        accept_window: int,
        want_truth: bool,
        behaviour: DriveBehaviour = REFERENCE,
    ) -> None:
        n = check_square(config.plant)
        if behaviour.restart_sequence_on_enable:
            raise ValueError("a multi-axis drive keeps one sequence for all axes: no restart on enable")
        self.node_ids = axis_node_ids(config.drive, n)
        self.n_axes = n
        plant, sim = config.plant, config.sim
        self.period_ns = plant.period_ns
        self.want_truth = want_truth
        cell_s = plant.period_s / sim.substeps
        self.disturbances = [
            Disturbance([d for d in sim.disturbances if d.input_index == i], cell_s) for i in range(n)
        ]
        for d in self.disturbances:
            d.origin_s = None  # zero until the first enable
        self.plant = CoupledPlantModel(plant, sim.substeps, InputDisturbances(self.disturbances),
                                       sim.initial_state)  # fmt: skip
        self.axes = [
            DriveCore(axis_config(config, i, node), accept_window=accept_window, want_truth=False,
                      behaviour=behaviour, plant_model=cast(PlantModel, _AxisOutput(self, i)),
                      disturbance=self.disturbances[i])
            for i, node in enumerate(self.node_ids)
        ]  # fmt: skip
        self.paths = [core.path for core in self.axes]
        self._axis_of = {}
        for i, core in enumerate(self.axes):
            self._axis_of[core.command_id] = i
            self._axis_of[core.control_id] = i
        self.rx_ids = frozenset(self._axis_of)
        self.feedback_ids = tuple(int(FrameKind.FEEDBACK) + node for node in self.node_ids)
        self.commanded = [False] * n  # a valid command per axis since the last period boundary
        self.stats = DriveStats()  # the clock's own counters (each axis has its core's)
        self.time_ns = 0
        self._physics_ok = True

    # --- state ---------------------------------------------------------------------------------
    @property
    def state(self) -> DriveState:
        states = [core.state for core in self.axes]
        if DriveState.FAULT in states:
            return DriveState.FAULT
        if all(s is DriveState.ENABLED for s in states):
            return DriveState.ENABLED
        return DriveState.DISABLED

    @property
    def states(self) -> tuple[DriveState, ...]:
        return tuple(core.state for core in self.axes)

    @property
    def period_index(self) -> int:
        return self.time_ns // self.period_ns

    @property
    def silent(self) -> bool:
        return any(core.silent for core in self.axes)

    @property
    def all_commanded(self) -> bool:
        return all(self.commanded)

    def axis_stats(self) -> list[DriveStats]:
        return [DriveStats(**vars(core.stats)) for core in self.axes]

    def start_disturbances(self, axis: int) -> None:
        origin = self.disturbances[axis].origin_s
        for d in self.disturbances:
            if d.origin_s is None:
                d.origin_s = origin
        self.plant.disturbance_changed()

    # --- frames --------------------------------------------------------------------------------
    def on_frame(self, arbitration_id: int, data: bytes | bytearray, t_ns: int) -> FrameResult:
        """Act on a frame for one of the axes at simulated time ``t_ns``."""
        axis = self._axis_of.get(arbitration_id)
        if axis is None:
            self.stats.frames_ignored += 1
            return FrameResult.IGNORED
        core = self.axes[axis]
        core.time_ns = self.time_ns
        result = core.on_frame(arbitration_id, data, t_ns)
        if result is FrameResult.COMMAND:
            self.commanded[axis] = True
        return result

    def axis_of(self, arbitration_id: int) -> int | None:
        return self._axis_of.get(arbitration_id)

    def take_outgoing(self) -> list[OutgoingId]:
        out: list[OutgoingId] = []
        for node, core in zip(self.node_ids, self.axes, strict=True):
            for kind, payload in core.take_outgoing():
                out.append((int(kind) + node, payload))
        return out

    def fault_all(self, code: FaultCode, info: int) -> None:
        for core in self.axes:
            core.fault(code, info, self.time_ns)

    # --- time ----------------------------------------------------------------------------------
    def integrate_to(self, t_ns: int) -> None:
        """Advance the coupled plant to ``t_ns``, switching each axis's current when it changes."""
        if self._physics_ok and self.time_ns < t_ns:
            try:
                self._integrate_to(t_ns)
            except (OverflowError, ValueError, FloatingPointError):
                self._physics_ok = False
                self.fault_all(FaultCode.ENCODER, 0)
        self.time_ns = max(self.time_ns, t_ns)
        for core in self.axes:
            core.time_ns = self.time_ns

    def _integrate_to(self, t_ns: int) -> None:
        paths, plant = self.paths, self.plant
        t = self.time_ns
        while t < t_ns:
            nxt = None
            for p in paths:
                p.apply_due(t)
                c = p.next_change_ns()
                if c is not None and (nxt is None or c < nxt):
                    nxt = c
            end = t_ns if nxt is None or nxt > t_ns else nxt
            plant.advance_vector(t, end, [p.held_A for p in paths])
            t = end
        if not plant.finite():
            raise OverflowError("the coupled plant left the float range")

    def period_boundary(self) -> None:
        """Close the period at :attr:`time_ns` on every axis (watchdog with its own commands)."""
        for i, core in enumerate(self.axes):
            core.period_boundary(self.commanded[i])
            self.commanded[i] = False

    def sample(self) -> tuple[list[OutgoingId], AxesTruth | None]:
        """Latch every encoder at :attr:`time_ns`: the FEEDBACK frames of all axes and the truth."""
        frames = [(fid, core.sample()[0]) for fid, core in zip(self.feedback_ids, self.axes, strict=True)]
        if not self.want_truth:
            return frames, None
        t = self.time_ns
        t_s = t * 1e-9
        truth = AxesTruth(
            t // self.period_ns,
            t,
            self.plant.state,
            tuple(d.value_A(t_s) for d in self.disturbances),
            tuple(p.held_A for p in self.paths),
            self.state,
        )
        return frames, truth
