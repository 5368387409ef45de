"""The safety envelope: [safety] parsing, the encoder-resolution refusal, trips in whole runs."""

from __future__ import annotations

import dataclasses
import re
import struct
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from dob_hil.config import Config, parse_config_text
from dob_hil.errors import ConfigError
from dob_hil.link.protocol import FrameKind
from dob_hil.log import read_log
from dob_hil.loop.envelope import SafetyConfig, SafetyTrip, check_encoder_resolution, max_output_speed
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path

A_POLE, B_GAIN = 128.59, 2.1484e4  # the paper's plant: v' = -a v + b u


def _with_safety(text: str) -> Config:
    return parse_config_text(scenario_path("paper-step").read_text() + "\n[safety]\n" + text)


def _ends_at_zero_and_disabled(path: Path) -> None:
    data = read_log(path)
    assert data.complete
    tx = data.frames[data.frames["direction"] == 1]
    last_cmd = tx[tx["arbitration_id"] == FrameKind.COMMAND + 1][-1]
    assert bytes(last_cmd["data"][:2]) == b"\x00\x00" and last_cmd["data"][2] & 0x80 == 0
    assert tx[-1]["arbitration_id"] == FrameKind.CONTROL + 1 and tx[-1]["data"][0] == 0


def test_safety_section_parses_and_names_bad_keys() -> None:
    c = _with_safety("max_abs_position = 5.0\nposition_window = [-1.0, 3.0]\nmax_abs_velocity = 50.0\n"
                     "max_tracking_error = 0.5\nmax_encoder_jumps = 3\n")  # fmt: skip
    assert c.safety == SafetyConfig(5.0, (-1.0, 3.0), 50.0, 0.5, 3)
    assert parse_config_text(scenario_path("paper-step").read_text()).safety == SafetyConfig()
    for bad, field in (("position_window = [3.0, 1.0]", "safety.position_window"),
                       ("max_abs_velocity = -1.0", "safety.max_abs_velocity"),
                       ("max_encoder_jumps = -1", "safety.max_encoder_jumps"),
                       ("max_speed = 1.0", "safety.max_speed")):  # fmt: skip
        with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
            _with_safety(bad)


def test_max_speed_of_the_paper_plant_is_b_over_a_times_the_limit(paper_step: Config) -> None:
    # v(t) = b I / a (1 - e^(-a t)): an independent closed form
    for horizon_s in (0.001, 0.01, 1.0):
        expected = B_GAIN * 0.7 / A_POLE * (1 - np.exp(-A_POLE * horizon_s))
        assert max_output_speed(paper_step, horizon_s)[0] == pytest.approx(expected, rel=1e-3)


def test_an_encoder_that_aliases_at_the_plants_speed_is_refused(paper_step: Config, log_path: Path) -> None:
    eight_bit = dataclasses.replace(paper_step, drive=dataclasses.replace(paper_step.drive, encoder_bits=8))
    with pytest.raises(ConfigError, match=r"drive\.encoder_bits: a 8-bit encoder .* reaches 117 rev/s"):
        check_encoder_resolution(eight_bit, 1.0)
    with pytest.raises(ConfigError, match="encoder_bits"):
        run_session(eight_bit, RunOptions(log_path=log_path))
    assert not log_path.exists()  # refused before anything was opened or enabled
    check_encoder_resolution(paper_step, 1.0)  # 32 bits: fine


@pytest.mark.parametrize(
    ("safety", "reason"),
    [
        ("max_abs_position = 0.5", r"safety envelope: position 0\.5\d* \(output 0\) outside \[-0\.5, 0\.5\]"),
        ("position_window = [-0.1, 0.8]", r"safety envelope: position 0\.8\d* \(output 0\) outside"),
        ("max_tracking_error = 0.5", r"safety envelope: tracking error .* beyond 0\.5 at sample 0"),
        ("max_abs_velocity = 5.0", r"safety envelope: velocity estimate .* beyond 5/s"),
    ],
)
def test_a_limit_trips_a_safe_stop_with_its_reason(safety: str, reason: str, log_path: Path) -> None:
    config = _with_safety(safety)
    with pytest.raises(SafetyTrip, match=reason):
        run_session(config, RunOptions(log_path=log_path))
    data = read_log(log_path)
    summary = data.metadata["summary"]
    assert summary["exit_reason"].startswith("safety envelope: ")
    assert int(summary["samples"]) < 3333
    assert [e["kind"] for e in data.events].count("safety_trip") == 1
    _ends_at_zero_and_disabled(log_path)


class SpoofedFeedback(can.BusABC):
    """The host's bus end with the drive's feedback counts replaced from frame ``start`` on by a
    spoofer that tracks the sequence numbers but reports positions of its own."""

    def __init__(self, inner: can.BusABC, start: int) -> None:
        self.inner, self.start, self.n = inner, start, 0
        super().__init__(channel="spoofed")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self.inner.recv(timeout)
        if msg is not None and msg.arbitration_id == FrameKind.FEEDBACK + 1:
            self.n += 1
            if self.n >= self.start:
                _counts, seq, status = struct.unpack("<iBB", msg.data)
                fake = struct.pack("<iBB", (1 if self.n % 2 else -1) * 1_500_000_000, seq, status)
                msg = can.Message(arbitration_id=msg.arbitration_id, data=fake, is_extended_id=False)
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[Any, bool]:
        return self.inner.recv(timeout), False

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()


def test_spoofed_feedback_ends_as_a_fault_not_a_success(paper_step: Config, log_path: Path) -> None:
    options = RunOptions(log_path=log_path, bus_wrapper=lambda bus: SpoofedFeedback(bus, 500))
    with pytest.raises(SafetyTrip, match=r"safety envelope: 1 encoder jump\(s\), at most 0"):
        run_session(paper_step, options)
    data = read_log(log_path)
    assert len(data.samples) <= 502  # stopped at the next sample
    _ends_at_zero_and_disabled(log_path)


def test_tolerated_encoder_jumps_are_counted_then_trip(paper_step: Config, log_path: Path) -> None:
    config = _with_safety("max_encoder_jumps = 3\nmax_abs_velocity = 1e12")
    options = RunOptions(log_path=log_path, bus_wrapper=lambda bus: SpoofedFeedback(bus, 500))
    with pytest.raises(SafetyTrip, match=r"4 encoder jump\(s\), at most 3"):
        run_session(config, options)


def test_a_diverging_unstable_plant_ends_as_a_fault(log_path: Path) -> None:
    # an open-loop unstable velocity pole (+40/s), gains from the DAREs, and a step of 100 rev:
    # saturated at 0.7 A the plant runs away; the default envelope (no [safety]) stops it
    text = scenario_path("paper-step").read_text().replace("A = [[0.0, 1.0], [0.0, -128.59]]",
                                                            "A = [[0.0, 1.0], [0.0, 40.0]]")  # fmt: skip
    text = re.sub(r"\n(Lc|Kc|Kdist) = .*", "", text).replace("position = 1.0", "position = 100.0")
    config = parse_config_text(text)
    with pytest.raises(SafetyTrip, match="safety envelope: "):
        run_session(config, RunOptions(log_path=log_path, duration_s=5.0))
    data = read_log(log_path)
    assert data.metadata["summary"]["exit_reason"].startswith("safety envelope: ")
    assert len(data.samples) < 5 * 3333
    _ends_at_zero_and_disabled(log_path)
