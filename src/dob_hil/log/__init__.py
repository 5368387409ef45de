"""The run log: MCAP, written by a separate process, read back as numpy structured arrays.

Channels (ros2msg schemas, little-endian CDR, fixed-size fields so every message of a channel
has the same length; fields ordered 8-, 4-, then 1-byte so CDR needs no padding):

=====================  ========================  ===============================================
topic                  schema                    one message per
=====================  ========================  ===============================================
``/dob_hil/sample``    ``dob_hil/msg/Sample``    control period (log time: the sample instant)
``/dob_hil/can``       ``dob_hil/msg/CanFrame``  raw CAN frame received or sent, data <= 8 bytes
``/dob_hil/can_fd``    ``dob_hil/msg/CanFdFrame``  CAN FD frame of 9..64 bytes (data uint8[64])
``/dob_hil/truth``     ``dob_hil/msg/GroundTruth``  simulated drive period (ground truth)
``/dob_hil/event``     ``dob_hil/Event`` (JSON)  state change, fault, overrun, warning,
                                                 ``log_overflow`` (records dropped)
=====================  ========================  ===============================================

The array sizes come from :class:`LogLayout` (n augmented states, m inputs, p outputs, plant
states); the message texts are in :mod:`dob_hil.log.schemas`. ROS 2 field names are lowercase,
so ``u_cmd_A`` is the field ``u_cmd_a``. Metadata records: ``log_format`` (dims and channel ids),
``versions``, ``run``, whatever the caller adds, and ``summary`` written at close (counts written,
records dropped, exit reason). Attachments: ``design.json``, ``config.toml`` (as given).

Record format between the control process and the writer process (:mod:`dob_hil.log.pipe`):
``<BQI`` (channel u8, log_time_ns u64, payload length u32) then the payload, which is the
message exactly as MCAP stores it (CDR header ``00 01 00 00`` + body, or JSON).

Use::

    with LogWriter(path, LogLayout(2, 1, 1, 2), metadata={"run": run_metadata(...)},
                   attachments={"design.json": text}) as log:
        log.sample(...); log.frame(msg, is_rx=True); log.flush()
    data = read_log(path)   # data.samples["x_hat"], data.frames, data.events, data.warnings
"""

from __future__ import annotations

from dob_hil.errors import LogWriteError
from dob_hil.log.metadata import run_metadata, versions_metadata
from dob_hil.log.reader import LogData, read_log
from dob_hil.log.schemas import LogLayout
from dob_hil.log.writer import LogStats, LogWriter

__all__ = [
    "LogData",
    "LogLayout",
    "LogStats",
    "LogWriteError",
    "LogWriter",
    "read_log",
    "run_metadata",
    "versions_metadata",
]
