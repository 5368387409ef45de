"""Checks of the host that runs the real-time loop: scheduling, memory locking, CPU frequency
and isolation, RT throttling, SocketCAN support and hardware timestamps."""

from __future__ import annotations

import errno
import os
import resource
import socket
import subprocess
from pathlib import Path

from dob_hil.doctor.result import Check, Status

SYS_CPU = Path("/sys/devices/system/cpu")


def socketcan_support() -> Check:
    """Whether this kernel offers SocketCAN (``socket(AF_CAN, SOCK_RAW, CAN_RAW)``)."""
    af_can = getattr(socket, "AF_CAN", None)
    if af_can is None:
        return Check("SocketCAN", Status.SKIP, "this Python has no AF_CAN (not Linux)")
    try:
        sock = socket.socket(af_can, socket.SOCK_RAW, getattr(socket, "CAN_RAW", 1))
    except OSError as exc:
        if exc.errno == errno.EAFNOSUPPORT:
            return Check(
                "SocketCAN",
                Status.SKIP,
                "not available in this kernel (socket(AF_CAN) fails with errno 97, EAFNOSUPPORT); "
                "SocketCAN checks do not apply here: use udp_multicast or virtual",
                "sudo modprobe can can_raw (on a kernel that has them)",
            )
        return Check("SocketCAN", Status.FAIL, f"socket(AF_CAN) fails: {exc}")
    sock.close()
    return Check("SocketCAN", Status.PASS, "the kernel offers AF_CAN raw sockets")


def hardware_timestamps(ethtool_text: str | None, dev: str) -> Check:
    """From ``ethtool -T DEV``: does the interface stamp received frames in hardware?"""
    if ethtool_text is None:
        return Check("hardware timestamps", Status.SKIP, "ethtool not available", "sudo apt install ethtool")
    if "hardware-receive" in ethtool_text or "SOF_TIMESTAMPING_RX_HARDWARE" in ethtool_text:
        return Check("hardware timestamps", Status.PASS, f"{dev} stamps received frames in hardware")
    return Check(
        "hardware timestamps",
        Status.WARN,
        f"{dev} has software receive timestamps only: feedback times include the host's interrupt latency",
    )


def sched_fifo_permission() -> Check:
    """Try SCHED_FIFO priority 1 on this process for an instant, then put the old policy back."""
    if not hasattr(os, "sched_setscheduler"):
        return Check("SCHED_FIFO", Status.SKIP, "no sched_setscheduler on this OS")
    old_policy = os.sched_getscheduler(0)
    old_param = os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except PermissionError:
        return Check(
            "SCHED_FIFO",
            Status.WARN,
            "not permitted: --sched-fifo will be refused (and reported) and the loop runs with "
            "the normal scheduler",
            "run as root, or: sudo setcap cap_sys_nice+ep $(readlink -f .venv/bin/python), "
            "or an rtprio limit in /etc/security/limits.conf",
        )
    except OSError as exc:
        return Check("SCHED_FIFO", Status.WARN, f"cannot set: {exc}")
    os.sched_setscheduler(0, old_policy, old_param)
    return Check("SCHED_FIFO", Status.PASS, "permitted (--sched-fifo will apply)")


def memory_lock() -> Check:
    soft, _hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if os.geteuid() == 0 or soft == resource.RLIM_INFINITY:
        return Check("memory lock", Status.PASS, "unlimited (root or RLIMIT_MEMLOCK unlimited)")
    if soft < 256 * 1024 * 1024:
        return Check(
            "memory lock",
            Status.WARN,
            f"RLIMIT_MEMLOCK {soft // 1024} KiB: pages of the loop can be swapped out",
            "add '<user> - memlock unlimited' to /etc/security/limits.conf and log in again",
        )
    return Check("memory lock", Status.PASS, f"RLIMIT_MEMLOCK {soft // (1024 * 1024)} MiB")


def cpu_governor(sys_cpu: Path = SYS_CPU) -> Check:
    governors = {}
    for path in sorted(sys_cpu.glob("cpu[0-9]*/cpufreq/scaling_governor")):
        try:
            governors[path.parent.parent.name] = path.read_text().strip()
        except OSError:
            continue
    if not governors:
        return Check("CPU governor", Status.SKIP, "no cpufreq in /sys (a VM, or a fixed CPU frequency)")
    slow = {cpu: g for cpu, g in governors.items() if g != "performance"}
    if slow:
        listed = ", ".join(f"{c}={g}" for c, g in slow.items())
        return Check(
            "CPU governor",
            Status.WARN,
            f"not 'performance' on {listed}: frequency changes add latency",
            "sudo cpupower frequency-set -g performance",
        )
    return Check("CPU governor", Status.PASS, f"'performance' on all {len(governors)} CPUs")


def isolated_cpus(sys_cpu: Path = SYS_CPU) -> Check:
    try:
        isolated = (sys_cpu / "isolated").read_text().strip()
    except OSError:
        return Check("isolated CPUs", Status.SKIP, "/sys/devices/system/cpu/isolated not readable")
    if not isolated:
        return Check(
            "isolated CPUs",
            Status.WARN,
            "none: the loop shares its CPU with everything else (pin it with --cpu N at least)",
            "boot with isolcpus=N nohz_full=N, then run with --cpu N",
        )
    return Check(
        "isolated CPUs", Status.PASS, f"isolated: {isolated} (run the loop with --cpu on one of them)"
    )


def rt_throttling(proc_sys: Path = Path("/proc/sys/kernel")) -> Check:
    try:
        runtime_us = int((proc_sys / "sched_rt_runtime_us").read_text())
        period_us = int((proc_sys / "sched_rt_period_us").read_text())
    except (OSError, ValueError):
        return Check("RT throttling", Status.SKIP, "sched_rt_runtime_us not readable")
    if runtime_us < 0:
        return Check("RT throttling", Status.PASS, "off (sched_rt_runtime_us = -1)")
    return Check(
        "RT throttling",
        Status.PASS,
        f"SCHED_FIFO tasks get {runtime_us / period_us:.0%} of each {period_us / 1000:g} ms: the loop "
        "sleeps between deadlines, so this only bites a spinning task",
    )


def run_tool(cmd: list[str]) -> str | None:
    """A tool's stdout, or None if it is missing or fails."""
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=5, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout if done.returncode == 0 else None
