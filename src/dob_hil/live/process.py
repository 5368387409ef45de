"""Start and stop the live-server process, and the pipe the tap feeds.

The process is started with ``spawn`` (a fresh interpreter: no threads or locks inherited from
the loop's process) before the drive is enabled, and the run waits until its server listens: a
port that cannot be served is a :class:`LiveError` (exit status 2) and the drive is never enabled.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import queue
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from dob_hil.errors import DobHilError
from dob_hil.live.tap import LiveTap, decimation_for
from dob_hil.log.schemas import LogLayout

DEFAULT_PORT = 8765
DEFAULT_RATE_HZ = 100.0
DEFAULT_PIPE_BYTES = 256 * 1024  # about 800 items of ~300 bytes: 8 s of a 100 Hz view
F_SETPIPE_SZ = 1031  # fcntl.F_SETPIPE_SZ (Linux; named in fcntl from Python 3.10 on Linux only)
START_TIMEOUT_S = 60.0  # a spawned interpreter importing the SDK, on a loaded machine
STOP_TIMEOUT_S = 30.0


def _set_pipe_size(fd: int, size: int) -> None:
    """Ask for a pipe of ``size`` bytes (Linux); elsewhere, or refused, the default stays."""
    import fcntl

    with contextlib.suppress(OSError):
        fcntl.fcntl(fd, F_SETPIPE_SZ, size)


class LiveError(DobHilError):
    """The live view cannot be served (bad option, port taken, SDK missing)."""


@dataclass(frozen=True)
class LiveOptions:
    """``dob-hil run --live [PORT]``: port 0 picks a free one (``on_ready`` is told which)."""

    port: int = DEFAULT_PORT
    host: str = "127.0.0.1"
    rate_hz: float = DEFAULT_RATE_HZ
    pipe_bytes: int = DEFAULT_PIPE_BYTES  # the pipe to the live process (the OS may round it)
    linger_s: float = 0.5  # after the run, before the server stops: viewers draw the end
    on_ready: Callable[[str, int], None] | None = None  # (host, port) once the server listens

    def check(self) -> None:
        if not 0 <= self.port <= 65535:
            raise LiveError(f"--live: port must be 0..65535, got {self.port}")
        if not (self.rate_hz > 0 and self.rate_hz <= 10_000):
            raise LiveError(f"--live-rate: must be > 0 and <= 10000 Hz, got {self.rate_hz}")
        if self.pipe_bytes < 4096:
            raise LiveError(f"live pipe: must hold >= 4096 bytes, got {self.pipe_bytes}")
        if not self.linger_s >= 0:
            raise LiveError(f"--live-linger: must be >= 0 s, got {self.linger_s}")


class LiveServer:
    """The live-server process and the tap that feeds it; a context manager."""

    def __init__(
        self,
        options: LiveOptions,
        layout: LogLayout,
        period_ns: int,
        design_json: str,
        run_meta: Mapping[str, str],
    ) -> None:
        options.check()
        try:
            import foxglove  # noqa: F401  (fail here, in this process, with a clear line)
        except ImportError as exc:
            raise LiveError("--live: needs the foxglove-sdk package (pip install 'dob-hil[live]')") from exc
        from dob_hil.live import server

        self.options = options
        ctx = multiprocessing.get_context("spawn")
        reader, self._writer = ctx.Pipe(duplex=False)
        _set_pipe_size(self._writer.fileno(), options.pipe_bytes)
        self._status: Any = ctx.Queue()
        self.tap = LiveTap(self._writer.fileno(), decimation_for(period_ns, options.rate_hz))
        self._proc = ctx.Process(
            target=server.serve,
            args=(
                reader,
                self._status,
                options.host,
                options.port,
                layout,
                design_json,
                dict(run_meta),
                options.linger_s,
            ),
            name="dob-hil-live",
            daemon=True,
        )
        self.port = 0
        self.closed_report: dict[str, int] | None = None
        self._closed = False
        self._proc.start()
        reader.close()  # the child has its own copy: the writer's close is then its end of input
        kind, value = self._wait_start()
        if kind != "ready":
            self._kill()
            raise LiveError(f"--live: cannot serve on {options.host}:{options.port}: {value}")
        self.port = int(value)
        if options.on_ready is not None:
            options.on_ready(options.host, self.port)

    def _wait_start(self) -> tuple[str, Any]:
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            try:
                kind, value = self._status.get(timeout=0.2)
                return str(kind), value
            except queue.Empty:
                pass
            if not self._proc.is_alive():
                self._kill()
                raise LiveError(
                    f"--live: the live server process ended at start (exit {self._proc.exitcode})"
                )
            if time.monotonic() > deadline:
                self._kill()
                raise LiveError(f"--live: the live server did not start within {START_TIMEOUT_S:.0f} s")

    def _kill(self) -> None:
        self._closed = True
        if self._proc.is_alive():
            self._proc.kill()
        self._proc.join(STOP_TIMEOUT_S)
        self._writer.close()

    def close(self) -> None:
        """After the run: close the pipe (the server's end of input), then wait for it (bounded)."""
        if self._closed:
            return
        self._closed = True
        self._writer.close()
        deadline = time.monotonic() + STOP_TIMEOUT_S + self.options.linger_s
        while time.monotonic() < deadline:  # a server that died mid-run is not waited for
            try:
                kind, value = self._status.get(timeout=0.2)
            except queue.Empty:
                if not self._proc.is_alive():
                    break
                continue
            if kind == "closed":
                self.closed_report = dict(value)
                break
        self._proc.join(STOP_TIMEOUT_S)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(STOP_TIMEOUT_S)

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
