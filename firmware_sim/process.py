"""``python -m firmware_sim`` as a child process: started, awaited until it listens, stopped cleanly.

Real-time tests and benchmarks run the simulated drive in its own process (as a real drive is its
own computer). :func:`standalone_drive` starts it, waits for the line the command prints once its
bus is open (a CONTROL enable sent before that would be lost), yields a :class:`StandaloneDrive`,
and on exit stops it with SIGINT so that it prints its summary (killed only if it does not stop).
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

READY_TEXT = "stop with SIGINT"  # printed by firmware_sim.cli once the bus is open
STOP_TIMEOUT_S = 10.0


@dataclass
class StandaloneDrive:
    proc: subprocess.Popen[bytes]
    stderr_path: Path
    stderr_text: str = ""  # the whole stderr, once stopped
    exit_status: int | None = None

    def alive(self) -> bool:
        return self.proc.poll() is None

    def poll(self) -> int | None:
        return self.proc.poll()

    def last_line(self) -> str:
        text = self.stderr_text or self._read()
        lines = [ln for ln in text.splitlines() if ln.strip()]
        return lines[-1] if lines else ""

    def _read(self) -> str:
        return self.stderr_path.read_text(errors="replace") if self.stderr_path.exists() else ""


def free_udp_multicast_channel() -> str:
    """A random multicast group of 239.74.163.0/24 on which a python-can udp_multicast bus opens.

    Raises RuntimeError naming why where udp_multicast cannot be used on this machine.
    """
    import can

    channel = f"239.74.163.{random.randint(10, 250)}"
    try:
        can.Bus(interface="udp_multicast", channel=channel).shutdown()
    except (OSError, can.CanError, ImportError, NotImplementedError, ValueError) as exc:
        raise RuntimeError(f"udp_multicast cannot be opened here: {exc}") from exc
    return channel


def drive_command(
    config: Path,
    interface: str,
    channel: str,
    *,
    spin_us: float | None = None,
    sched_fifo: bool = False,
    cpus: Sequence[int] = (),
    truth_port: int | None = None,
) -> list[str]:
    cmd = [sys.executable, "-m", "firmware_sim", str(config), "-i", interface, "-c", channel]
    if spin_us is not None:
        cmd += ["--spin-us", f"{spin_us:g}"]
    if sched_fifo:
        cmd += ["--sched-fifo"]
    for cpu in cpus:
        cmd += ["--cpu", str(cpu)]
    if truth_port is not None:
        cmd += ["--truth-port", str(truth_port)]
    return cmd


def _wait_ready(drive: StandaloneDrive, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = drive._read()
        if READY_TEXT in text:
            return
        if drive.proc.poll() is not None:
            raise RuntimeError(f"firmware_sim exited with status {drive.proc.returncode}: {text.strip()}")
        time.sleep(0.02)
    raise RuntimeError(f"firmware_sim did not report ready within {timeout_s:g} s: {drive._read().strip()}")


@contextmanager
def standalone_drive(
    config: Path,
    interface: str,
    channel: str,
    *,
    spin_us: float | None = None,
    sched_fifo: bool = False,
    cpus: Sequence[int] = (),
    truth_port: int | None = None,
    env: Mapping[str, str] | None = None,
    ready_timeout_s: float = 30.0,
) -> Iterator[StandaloneDrive]:
    """The simulated drive in its own process, from ready to stopped (see the module docstring)."""
    cmd = drive_command(
        config, interface, channel, spin_us=spin_us, sched_fifo=sched_fifo, cpus=cpus, truth_port=truth_port
    )
    fd, name = tempfile.mkstemp(prefix="firmware_sim-", suffix=".stderr")
    stderr_path = Path(name)
    with os.fdopen(fd, "wb") as err:
        proc = subprocess.Popen(
            cmd, env=None if env is None else dict(env), stdout=subprocess.DEVNULL, stderr=err
        )
    drive = StandaloneDrive(proc, stderr_path)
    try:
        _wait_ready(drive, ready_timeout_s)
        yield drive
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        drive.exit_status = proc.returncode
        drive.stderr_text = drive._read()
        stderr_path.unlink(missing_ok=True)
