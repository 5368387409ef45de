"""The CANopen CiA 402 profile (cyclic synchronous torque): codec, options and the host link.

The simulated counterpart lives in ``firmware_sim.cia402``; the generic EDS shipped here
(``generic_cia402.eds``) describes it and serves as an example for a real drive.
"""
