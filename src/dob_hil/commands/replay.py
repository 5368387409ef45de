"""``dob-hil replay LOG.mcap --verify | --design OTHER | --to-bus [-i/-c/-b] [--json]``.

* ``--verify``: re-run the logged controller over the logged measurements and check every
  command and estimate bit for bit (:func:`dob_hil.analysis.replay.verify`). Exit 0 if identical,
  1 if not (the first mismatches and a count per field are printed).
* ``--design OTHER`` (a config path or a scenario name): what that design would have commanded
  on the same measurements, open loop, against what was sent; writes
  ``<log stem>-replay-<design name>.png`` beside the log.
* ``--to-bus``: play the recorded frames onto a python-can bus with their original timing
  (:mod:`dob_hil.analysis.playback`); the bus from -i/-c/-b or python-can's configuration.

``--json`` prints one JSON object on stdout instead of the text report. Exit 2 (one line on
stderr) for a log or design that cannot be used.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dob_hil.analysis.loaded import LoadedLog, load_log
from dob_hil.errors import LogReadError

if TYPE_CHECKING:
    from dob_hil.design import Design


def _warn(log: LoadedLog) -> None:
    for warning in log.warnings:
        print(f"dob-hil replay: warning: {log.path}: {warning}", file=sys.stderr)


def _no_samples(log: LoadedLog, what: str) -> LogReadError:
    """The one line for a log without samples: its warnings (a truncation, say) in the line."""
    why = f" ({'; '.join(log.warnings)})" if log.warnings else ""
    return LogReadError(f"{log.path}: the log holds no samples{why}: nothing to {what}")


def _verify(log: LoadedLog, as_json: bool) -> int:
    from dob_hil.analysis.replay import verify
    from dob_hil.analysis.verify_fast import verify_streaming

    # streamed and vectorised (bounded memory); the chained re-run decides anything else
    result = verify_streaming(log) or verify(load_log(log.path))
    if result.samples == 0:
        raise _no_samples(log, "verify")
    _warn(log)
    if as_json:
        print(json.dumps({"mode": "verify", "log": str(log.path), **result.to_dict()}, indent=1))
    else:
        verdict = "identical" if result.identical else "DIFFERENT"
        print(
            f"replay --verify {log.path}: {result.samples} samples, "
            f"DOB {'on' if result.dob_enabled else 'off'}: {verdict}"
        )
        print(f"  fields compared bit for bit: {', '.join(result.fields)}")
        if not result.identical:
            print(f"  {result.mismatched_samples} sample(s) differ, first at seq {result.first_mismatch_seq}")
            counts = ", ".join(f"{k} {v}" for k, v in result.mismatches_by_field.items() if v)
            print(f"  per field: {counts}")
            for mm in result.first_mismatches:
                print(f"  seq {mm.seq:>8} {mm.field:<12} logged {mm.logged}  replayed {mm.replayed}")
        for note in result.notes:
            print(f"  note: {note}")
    return 0 if result.identical else 1


def _design(log: LoadedLog, other: str, as_json: bool) -> int:
    """``--design``: the samples streamed block by block (memory bounded whatever the log's length)."""
    from dob_hil.analysis.replay import redesign_blocks
    from dob_hil.analysis.replay_plot import plot_redesign
    from dob_hil.log.schemas import TOPIC_SAMPLE
    from dob_hil.log.stream import open_stream, return_large_buffers_to_the_os

    return_large_buffers_to_the_os()
    design = load_other_design(other, log.dob_enabled)
    with open_stream(log.path, {TOPIC_SAMPLE: None}, events=False) as stream:  # one map of the file
        blocks = (b.samples for b in stream.blocks())
        total = stream.counts.get(TOPIC_SAMPLE, 0)  # from the message indexes
        result = redesign_blocks(log, blocks, design, total_samples=total)
    if result.samples == 0:
        raise _no_samples(log, "re-run")
    _warn(log)
    plot_path = log.path.with_name(f"{log.path.stem}-replay-{design.name}.png")
    assert result.series is not None
    plot_redesign(log, result.series, design.name, plot_path)
    out: dict[str, Any] = {
        "mode": "design",
        "log": str(log.path),
        "design": other,
        **result.to_dict(),
        "plot": str(plot_path),
    }
    if as_json:
        print(json.dumps(out, indent=1))
    else:
        print(
            f"replay --design {other} on {log.path} ({result.samples} samples, "
            f"DOB {'on' if result.dob_enabled else 'off'}), open loop on the recorded measurements:"
        )
        print(
            f"  applied current: sent rms {result.sent_rms_A:.5g} A, "
            f"{design.name} rms {result.other_rms_A:.5g} A"
        )
        print(
            f"  difference (other - sent): applied rms {result.u_applied_diff_rms_A:.5g} A, "
            f"max {result.u_applied_diff_max_A:.5g} A; commanded rms {result.u_cmd_diff_rms_A:.5g} A, "
            f"max {result.u_cmd_diff_max_A:.5g} A"
        )
        if len(result.sent_rms_A_per_input) > 1:  # several inputs: each axis
            for j, (sent, other_rms, diff_rms, diff_max) in enumerate(
                zip(
                    result.sent_rms_A_per_input,
                    result.other_rms_A_per_input,
                    result.u_applied_diff_rms_A_per_input,
                    result.u_applied_diff_max_A_per_input,
                    strict=True,
                )
            ):
                print(
                    f"  input {j + 1}: sent rms {sent:.5g} A, {design.name} rms {other_rms:.5g} A, "
                    f"difference rms {diff_rms:.5g} A, max {diff_max:.5g} A"
                )
        print(f"  {design.name} saturated {100.0 * result.other_saturated_fraction:.2f} % of samples")
        for note in result.notes:
            print(f"  note: {note}")
        print(f"  plot: {plot_path}")
    return 0


def load_other_design(other: str, dob_enabled: bool) -> Design:
    """``--design OTHER``: a design file written by ``dob-hil design`` (JSON), or a config (a TOML
    path or a shipped scenario name) designed here. Either must be stable with the log's DOB
    setting."""
    from dob_hil.config import load_config
    from dob_hil.design import Design, build_design
    from dob_hil.scenarios import resolve_config_path

    path = Path(other)
    if path.is_file() and _looks_like_json(path):
        design = Design.load(path)
        design.require_stable(dob_enabled)
        return design
    return build_design(load_config(resolve_config_path(other)), dob_enabled=dob_enabled)


def _looks_like_json(path: Path) -> bool:
    if path.suffix.lower() == ".json":
        return True
    try:
        with path.open("rb") as f:
            head = f.read(64).lstrip()
    except OSError:
        return False
    return head.startswith(b"{")


def _to_bus(path: Path, args: argparse.Namespace) -> int:
    """``--to-bus``: the log streamed (:mod:`dob_hil.analysis.playback`), memory bounded whatever
    its length; everything is checked before the bus is opened."""
    from dob_hil.analysis.playback import LogFrames, plan_playback, play
    from dob_hil.link.bus import open_bus
    from dob_hil.log.schemas import CAN_RX, CAN_TX
    from dob_hil.log.stream import return_large_buffers_to_the_os

    return_large_buffers_to_the_os()
    source = LogFrames(path)
    # rx: what the drive sent (a drive stand-in); tx: what we sent
    direction = {"rx": CAN_RX, "tx": CAN_TX}.get(args.direction)
    plan = plan_playback(source, direction)
    for warning in source.warnings:
        print(f"dob-hil replay: warning: {path}: {warning}", file=sys.stderr)
    if plan.frames == 0:
        print(f"dob-hil replay: {path}: the log holds no frames; nothing sent", file=sys.stderr)
        return 0
    if plan.refusal is not None:  # before the bus is opened: a damaged log sends nothing
        raise plan.refusal
    from dob_hil.loop.rt_os import RtSettings, apply_rt_settings, restore_rt_settings

    rt = RtSettings(
        sched_fifo=args.sched_fifo, cpus=tuple(args.cpu) if args.cpu else None, freeze_gc=args.freeze_gc
    )
    bus = open_bus(args.interface, args.channel, args.bitrate)
    cpus_before = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    report = apply_rt_settings(rt)
    for refused in report.refused:
        print(f"dob-hil replay: warning: {refused}", file=sys.stderr)
    try:
        print(
            f"dob-hil replay: sending {plan.frames} recorded frames onto "
            f"{bus.channel_info} with their original timing",
            file=sys.stderr,
        )
        stats = play(bus, source, plan, spin_ns=0 if args.no_spin else 150_000)
    finally:
        restore_rt_settings(rt)
        if cpus_before is not None and rt.cpus:
            os.sched_setaffinity(0, cpus_before)
        bus.shutdown()
    d = stats.to_dict()
    if args.json:
        print(json.dumps({"mode": "to-bus", "log": str(path), **d}, indent=1))
    else:
        lat = stats.lateness_us or {}
        print(
            f"replay --to-bus {path}: {stats.frames_sent} frames over {stats.duration_s:.3f} s; "
            f"lateness p50 {lat.get('p50', 0):.1f} us, p99 {lat.get('p99', 0):.1f} us, "
            f"max {lat.get('max', 0):.1f} us; {stats.late_frames} more than "
            f"{stats.late_threshold_us:g} us late"
        )
        if stats.recorded_gap_us and stats.sent_gap_us:
            rec, sent = stats.recorded_gap_us, stats.sent_gap_us
            print(
                f"  id 0x{stats.gap_id:X} gap: recorded p50 {rec['p50']:.1f} us p99 {rec['p99']:.1f} us; "
                f"sent p50 {sent['p50']:.1f} us p99 {sent['p99']:.1f} us"
            )
        if stats.skipped_error_frames or stats.skipped_own_echoes:
            print(
                f"  skipped: {stats.skipped_error_frames} error frames, "
                f"{stats.skipped_own_echoes} received copies of own frames"
            )
    return 0


def main(args: argparse.Namespace) -> int:
    if args.verify or args.design:  # the samples are streamed: read the events, metadata, attachments
        from dob_hil.log.schemas import TOPIC_EVENT

        log = load_log(Path(args.log), topics=[TOPIC_EVENT])
        if args.verify:
            return _verify(log, args.json)
        return _design(log, args.design, args.json)
    return _to_bus(Path(args.log), args)  # streamed: the frames only
