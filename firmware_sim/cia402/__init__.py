"""A simulated CiA 402 servo drive (cyclic synchronous torque) for dob_hil's ``cia402`` profile.

A CANopen slave built on the ``canopen`` package's :class:`canopen.LocalNode` (SDO server, object
dictionary of the shipped generic EDS, NMT slave), with the firmware_sim physics (plant, encoder,
disturbances, injected faults, ground truth) behind the CiA 402 power state machine.

Timing contract with the host (the host is the clock; one SYNC per period):

* at SYNC k (``t_k``): the physics is integrated from ``t_{k-1}`` to ``t_k`` with the torque
  active since SYNC k-1; the position is sampled and the synchronous TPDOs go out; then the values
  of the last RPDO received since SYNC k-1 become active (controlword, target torque). A setpoint
  computed from TPDO k therefore acts from ``t_{k+1}``: one period of input delay.
* lockstep: the first SYNC is t = 0, each later SYNC (and each :meth:`advance_period`) is one
  period later (no wall clock); real time: a SYNC acts at its arrival on the drive's monotonic
  clock (see :mod:`firmware_sim.cia402.realtime`).

``SimulatedCia402Drive(bus, config, clock="lockstep"|"realtime", truth_sink=None)`` implements
:class:`dob_hil.profiles.base.SimulatedCounterpart`.
"""

from __future__ import annotations

from firmware_sim.cia402.drive import SimulatedCia402Drive

__all__ = ["SimulatedCia402Drive"]
