"""``dob-hil run --live``: the run served to Foxglove over its WebSocket protocol, off the loop.

:mod:`~dob_hil.live.tap` hands every Nth sample (and every event) from the log writer to a
non-blocking pipe without ever waiting; :mod:`~dob_hil.live.server` is the process that owns the
``foxglove-sdk`` WebSocket server; :mod:`~dob_hil.live.process` starts and stops it.
"""
