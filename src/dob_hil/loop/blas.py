"""One BLAS thread while a session runs: no busy-waiting BLAS workers beside the loop.

numpy and scipy bring their own OpenBLAS, which starts one worker thread per CPU. After a call it
spread over its workers they keep spinning, waiting for more work, for a while before they sleep
(OpenBLAS's default), and that CPU time is taken from the loop and the log writer. The design's
and the plant's matrices have at most a few dozen rows, which one thread computes at least as fast,
so a session limits BLAS to one thread from the design to the drive's stop (``threadpoolctl``, the
library made for it, reaching every BLAS loaded in the process: numpy's and scipy's).

Measured on a 2-CPU machine (BENCHMARKS.md, "Issue 16 lockstep, sixth pass"): without the limit
the first 8,000 lockstep samples of every session ran 20-30 ms slower in wall time than on this
thread's CPU clock, with the process using up to 2.3 times the loop's CPU; with it, wall and CPU
time agree from the first sample. The log writer process is started with one BLAS thread for the
same reason (``dob_hil.log.writer.WRITER_THREAD_ENV``).
"""

from __future__ import annotations

from contextlib import AbstractContextManager

# scipy.linalg loads scipy's own OpenBLAS: loaded here, before a limit is set, so that the limit
# reaches it (threadpoolctl limits the libraries loaded at the time of the call; one imported
# later, as a session's first scipy call would, starts with all its threads)
import scipy.linalg  # noqa: F401
from threadpoolctl import threadpool_limits


def one_blas_thread() -> AbstractContextManager[object]:
    """Limit every loaded BLAS to one thread until the context ends (the previous limits return)."""
    limits: AbstractContextManager[object] = threadpool_limits(limits=1, user_api="blas")
    return limits
