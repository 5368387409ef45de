"""The heap as the loop starts, out of the garbage collector's way while the loop runs.

By the time the loop starts, a session holds hundreds of thousands of objects it made once: the
imported modules, the design, the drive's configuration (a CiA 402 object dictionary parsed from
its EDS), the log's schemas. The loop then allocates a few dozen short-lived objects per sample
(frames, tuples, floats). CPython's collector, triggered by those allocations, also examines the
setup's objects that are still in its young generations and promotes them, and a full collection
would walk all of them: tens of milliseconds at once, a missed deadline in a real-time run.

:func:`frozen_heap` moves every object alive when the loop starts to the collector's permanent
generation (``gc.freeze``) and returns them when it ends (``gc.unfreeze``): during the loop the
collector sees only what the loop allocates. Nothing is collected less: garbage made before the
loop waits until after it. Measured (BENCHMARKS.md, "Issue 16 lockstep, seventh pass"): about 2 %
of a lockstep CiA 402 sample, 1 % of a native one.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def frozen_heap() -> Iterator[None]:
    """Every object tracked now in the permanent generation until the context ends. Where objects
    are frozen already (by the application, or an enclosing session), nothing is done: ``gc`` can
    only unfreeze them all, which would undo the other freeze."""
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
