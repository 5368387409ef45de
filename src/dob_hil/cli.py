"""``dob-hil``: the command line. Argument parsing is split from running so both are testable.

Heavy modules (numpy, scipy, control, can, mcap, matplotlib) are imported inside the handlers,
so ``dob-hil --help`` stays fast.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from importlib import import_module

from dob_hil import __version__
from dob_hil.errors import DobHilError

# Each subcommand: (module with a main(args) -> int, help).
_COMMANDS: dict[str, tuple[str, str]] = {
    "design": ("dob_hil.commands.design", "design the controller from a config and report it"),
    "run": ("dob_hil.commands.run", "run the controller against a drive (default: simulated)"),
    "demo": ("dob_hil.commands.demo", "the paper's step scenario with and without the DOB"),
    "analyze": ("dob_hil.commands.analyze", "metrics and plots from MCAP logs"),
    "replay": ("dob_hil.commands.replay", "re-run, re-design or re-send a logged run"),
    "export": ("dob_hil.commands.export", "a log's frames as BLF/ASC/CSV, or the log in another layout"),
    "doctor": ("dob_hil.commands.doctor", "check the CAN interface and the host before a real-time run"),
    "campaign": ("dob_hil.commands.campaign", "robustness campaign: many lockstep runs, a table, a report"),
    "config": ("dob_hil.commands.config", "the config reference (--doc) or a commented starter (--template)"),
    "init": ("dob_hil.commands.config", "write a commented starter config to a new file"),
    "profiles": ("dob_hil.commands.profiles", "the drive profiles and the bus load each gives for a config"),
}


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """python-can's usual bus options; omitted values come from python-can's config/env."""
    parser.add_argument("-i", "--interface", help="python-can interface (socketcan, udp_multicast, ...)")
    parser.add_argument("-c", "--channel", help="python-can channel (vcan0, 239.74.163.2, ...)")
    parser.add_argument("-b", "--bitrate", type=int, help="bus bitrate in bit/s")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dob-hil",
        description="Hardware-in-the-loop bridge: a discrete-time state-space disturbance "
        "observer controller (Lee, Kim, Baek, ACC 2000) against a servo drive over CAN.",
    )
    parser.add_argument("--version", action="version", version=f"dob-hil {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in _COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        _add_arguments(name, p)
    return parser


def _add_arguments(name: str, p: argparse.ArgumentParser) -> None:
    # Arguments are declared here (not in the command modules) so --help imports nothing heavy.
    if name == "design":
        p.add_argument("config", help="TOML config (or a scenario name such as paper-step)")
        p.add_argument("--json", action="store_true", help="print the report as JSON on stdout")
        p.add_argument("--out", help="output folder for the design file and plots")
        p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
        p.add_argument(
            "--optimize",
            action="store_true",
            help="choose Kdist (tune = all: Lc, Kc too) for the best rejection per [design.optimize]",
        )
    elif name == "run":
        p.add_argument("config", nargs="?", help="TOML config file")
        p.add_argument("--scenario", help="a shipped scenario: paper-step or paper-sine")
        add_bus_arguments(p)
        p.add_argument(
            "--no-dob",
            action="store_true",
            help="switch the disturbance observer off (default: run.dob_enabled)",
        )
        p.add_argument(
            "--duration", type=float, help="run length in seconds (default: the config's run.duration_s)"
        )
        p.add_argument(
            "--log", help="MCAP log path (default: <run.log_dir>/<name>-<dob|nodob>-<UTC time>.mcap)"
        )
        p.add_argument("--no-log", action="store_true", help="run without a log file (quick runs, campaigns)")
        p.add_argument(
            "--log-layout",
            choices=("samples", "blocks"),
            default=None,
            help="the log's messages: one per record (samples, Foxglove plots them against time) or "
            "runs of records (blocks, about 40%% smaller); default: the config's run.log_layout",
        )
        p.add_argument(
            "--realtime",
            action="store_true",
            help="real-time loop even without a bus (embedded drive on its own clock)",
        )
        p.add_argument("--sched-fifo", action="store_true", help="SCHED_FIFO where permitted (default: off)")
        p.add_argument(
            "--cpu", type=int, action="append", help="pin the loop to this CPU; repeatable (default: any)"
        )
        p.add_argument("--freeze-gc", action="store_true", help="gc.freeze() and gc.disable() (default: off)")
        p.add_argument(
            "--clear-fault",
            action="store_true",
            help="send ClearFault before enabling (a drive left in FAULT, e.g. by a killed run)",
        )
        p.add_argument(
            "--feedback-timeout-periods",
            type=int,
            help="host timeout: periods without feedback that end the run (drive.feedback_timeout_periods)",
        )
        p.add_argument(
            "--watchdog-periods",
            type=int,
            help="the embedded drive's command watchdog (drive.watchdog_periods; for a drive in "
            "another process, give it there: python -m firmware_sim --watchdog-periods)",
        )
        p.add_argument(
            "--progress",
            action="store_true",
            help="draw the progress bar even when stderr is not a terminal (default: terminal only)",
        )
        p.add_argument(
            "--no-progress",
            action="store_true",
            help="no progress bar (drawn only on a terminal, after 0.5 s)",
        )
        p.add_argument("--json", action="store_true", help="print the summary as JSON (default: text)")
        p.add_argument(
            "--live",
            nargs="?",
            type=int,
            const=8765,
            metavar="PORT",
            help="serve the run to Foxglove over WebSocket (default port 8765; 0: any free port)",
        )
        p.add_argument("--live-host", default="127.0.0.1", help="--live: address to bind (default 127.0.0.1)")
        p.add_argument(
            "--live-rate", type=float, default=100.0, help="--live: samples per second sent (default 100)"
        )
    elif name == "demo":
        p.add_argument("--scenario", default="paper-step", help="scenario to run (default paper-step)")
        p.add_argument("--out", default="logs", help="folder for logs and plots")
    elif name == "analyze":
        p.add_argument("logs", nargs="+", help="one or more MCAP logs")
        p.add_argument("--json", action="store_true", help="print the metrics as JSON on stdout")
        p.add_argument(
            "--from",
            dest="from_s",
            type=float,
            default=0.1,
            help="start of the metrics window in seconds (default 0.1)",
        )
        p.add_argument("--plots", help="folder for the PNG plots (default: beside the log)")
        p.add_argument("--no-plots", action="store_true", help="skip the plots")
        p.add_argument(
            "--plot-window",
            metavar="START:END",
            help="plot only this stretch, in seconds from the first sample (default: all of a log up to "
            "100,000 samples; the first 100,000 samples of a longer one)",
        )
    elif name == "replay":
        p.add_argument("log", help="MCAP log")
        g = p.add_mutually_exclusive_group(required=True)
        g.add_argument("--verify", action="store_true", help="check every command bit for bit")
        g.add_argument(
            "--design",
            help="a design.json (from dob-hil design), a config file or a scenario name: "
            "what that design would have commanded",
        )
        g.add_argument("--to-bus", action="store_true", help="play the raw frames onto a bus")
        add_bus_arguments(p)
        p.add_argument(
            "--direction",
            choices=("both", "rx", "tx"),
            default="both",
            help="--to-bus: which recorded frames to send: rx (the drive's, to stand in for it), "
            "tx (our commands: a live drive on that bus would act on them!), or both (default)",
        )
        p.add_argument("--sched-fifo", action="store_true", help="--to-bus: SCHED_FIFO where permitted")
        p.add_argument("--cpu", type=int, action="append", help="--to-bus: pin the sender to this CPU")
        p.add_argument("--freeze-gc", action="store_true", help="--to-bus: gc.freeze() and gc.disable()")
        p.add_argument(
            "--no-spin",
            action="store_true",
            help="--to-bus: sleep to each deadline without spinning the last 150 us (gentler on a "
            "shared CPU, later frames)",
        )
        p.add_argument("--json", action="store_true", help="print the result as JSON")
    elif name == "doctor":
        _add_doctor_arguments(p)
    elif name == "export":
        p.add_argument("log", help="MCAP log")
        p.add_argument("--format", required=True, choices=("blf", "asc", "csv", "mcap"))
        p.add_argument("--out", help="output path (default: beside the log)")
        p.add_argument("--samples", action="store_true", help="csv: the samples, not the frames")
        p.add_argument(
            "--log-layout",
            choices=("samples", "blocks"),
            help="mcap: the whole log rewritten in this message layout (samples: Foxglove plots every "
            "field against time; blocks: about 40%% smaller)",
        )
    elif name == "campaign":
        _add_campaign_arguments(p)
    elif name == "profiles":
        p.add_argument("config", nargs="?", help="TOML config or scenario: bus load of each profile for it")
        p.add_argument("--json", action="store_true", help="print the catalogue as JSON")
        p.add_argument("--markdown", action="store_true", help="print the README's catalogue table")
    elif name == "config":
        g = p.add_mutually_exclusive_group(required=True)
        g.add_argument("--doc", action="store_true", help="the reference of every key (Markdown)")
        g.add_argument("--template", action="store_true", help="a commented starter config (TOML)")
        p.add_argument("--out", help="write to this new file instead of stdout")
    elif name == "init":
        p.add_argument("path", help="the config file to create (refused if it exists)")


def _add_campaign_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="campaign TOML (campaigns/paper-robustness.toml)")
    p.add_argument("--workers", type=int, help="processes (default: the CPUs available; 1: serial)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--scheduler", help="run on this Dask scheduler (tcp://host:8786)")
    g.add_argument("--local-cluster", action="store_true", help="run on a Dask LocalCluster of --workers")
    p.add_argument("--rerun", metavar="CASE_ID", help="re-run one case with its log, compare with the table")
    p.add_argument("--out", help="output folder (default: logs/campaign-<name>)")
    p.add_argument("--no-report", action="store_true", help="skip report.md and the plots")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def _add_doctor_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="config or scenario whose drive.bitrate_bps to expect")
    add_bus_arguments(p)
    p.add_argument("--data-bitrate", type=int, help="CAN FD data bitrate to expect, bit/s")
    p.add_argument("--json", action="store_true", help="print the checks as JSON")
    p.add_argument("--ip-link-file", help="check recorded 'ip -details -statistics link show DEV' output")
    p.add_argument("--ethtool-file", help="with --ip-link-file: recorded 'ethtool -T DEV' output")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_module", None):
        parser.print_help()
        return 2
    command = args.command
    # Warnings (e.g. a design violating a robustness bound) as one line each, like errors.
    warnings.formatwarning = lambda message, *_a, **_k: f"dob-hil {command}: warning: {message}\n"
    try:
        module = import_module(args._module)
        run: Callable[[argparse.Namespace], int] = module.main
        status = run(args)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return status
    except DobHilError as exc:
        print(f"dob-hil {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dob-hil {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader of stdout went away (``dob-hil analyze x.mcap | head``): whatever the command
        # did is done (a run's log is closed); stop writing, quietly, as a piped Unix tool does
        _silence_stdout()
        return 141  # 128 + SIGPIPE
    except Exception as exc:
        if _is_numerical_failure(exc):
            print(
                f"dob-hil {args.command}: error: numerical failure in the design ({exc}); "
                "check the plant and gain magnitudes",
                file=sys.stderr,
            )
            return 2
        raise


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # pragma: no cover - stdout without a file descriptor
        pass


def _is_numerical_failure(exc: Exception) -> bool:
    """numpy's LinAlgError: the one guarded call site for the design's numerics (a config that
    passes the parser's bounds but still makes an eigenvalue or DARE routine fail)."""
    numpy = sys.modules.get("numpy")
    return numpy is not None and isinstance(exc, numpy.linalg.LinAlgError)


if __name__ == "__main__":
    sys.exit(main())
