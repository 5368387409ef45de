"""Whole lockstep runs of the CiA 402 profile against firmware_sim's CiA 402 drive, checked through
the log: tracking against the native scenarios and against --no-dob (true position), every frame
decoded by canopen's own PDO maps, the safe stop, a drive fault with its EMCY code, the CLI."""

from __future__ import annotations

import threading
from pathlib import Path

import canopen
import numpy as np
import pytest

from dob_hil.cli import main
from dob_hil.config import Config, load_config, parse_config_text
from dob_hil.design import Design
from dob_hil.design.discretize import zoh
from dob_hil.errors import DriveFault
from dob_hil.link.cia402 import codec
from dob_hil.link.cia402.options import DEFAULT_EDS
from dob_hil.log import LogData, read_log
from dob_hil.log.schemas import FLAG_SATURATED
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path

NODE = 1
LIMIT_CODE = 1399  # floor(0.7 A / 0.0005 A)
N = 3333


def _tracking_error_rms(data: LogData, from_s: float = 0.1) -> float:
    s, t = data.samples, data.truth
    true_pos = t["state"][: len(s), 0]  # truth period_index k is the state at sample k
    assert np.array_equal(t["period_index"][: len(s)], s["seq"])
    window = s["time_ns"] >= from_s * 1e9
    err = s["x_ref"][window, 0] - true_pos[window]
    return float(np.sqrt(np.mean(err**2)))


def _run(config: Config, path: Path, **kw: object) -> LogData:
    run_session(config, RunOptions(log_path=path, **kw))  # type: ignore[arg-type]
    return read_log(path)


@pytest.fixture(scope="module")
def step_cia402() -> Config:
    return load_config(scenario_path("paper-step-cia402"))


def _frames(data: LogData, aid: int, tx: bool) -> np.ndarray:
    f = data.frames
    return f[(f["direction"] == (1 if tx else 0)) & (f["arbitration_id"] == aid)]


def test_paper_step_cia402_logs_every_sample_and_frame(step_cia402: Config, tmp_path: Path) -> None:
    data = _run(step_cia402, tmp_path / "run.mcap")
    assert data.complete and data.metadata["summary"]["exit_reason"] == "completed"
    s = data.samples
    assert len(s) == N
    np.testing.assert_array_equal(s["seq"], np.arange(N))
    np.testing.assert_array_equal(s["time_ns"], np.arange(N) * 300_000)
    assert np.abs(s["dac_counts"]).max() <= LIMIT_CODE and np.abs(s["u_applied_a"]).max() <= 0.7
    np.testing.assert_array_equal(s["u_applied_a"][:, 0], s["dac_counts"][:, 0] * 0.0005)
    sat = (s["flags"] & FLAG_SATURATED) != 0
    assert sat.any() and np.all(np.abs(s["dac_counts"][sat, 0]) == LIMIT_CODE)
    # canopen's PDO maps decode what went over the wire (an independent decoder)
    node = canopen.RemoteNode(NODE, str(DEFAULT_EDS))
    rpdo, tpdo = node.rpdo.map[1], node.tpdo.map[1]
    for pdo_map, objects, cob_id in ((rpdo, (0x6040, 0x6071), codec.RPDO1_BASE + NODE),
                                     (tpdo, (0x6041, 0x6064), codec.TPDO1_BASE + NODE)):  # fmt: skip
        pdo_map.clear()
        pdo_map.cob_id = cob_id
        for index in objects:
            pdo_map.add_variable(index)
    tx_rpdo = _frames(data, codec.RPDO1_BASE + NODE, tx=True)
    rx_tpdo = _frames(data, codec.TPDO1_BASE + NODE, tx=False)
    assert len(_frames(data, codec.SYNC_ID, tx=True)) == N + 3  # one per sample, three in the stop
    assert len(rx_tpdo) >= N and len(tx_rpdo) == N + 3
    torque, controlword, position, statusword = [], [], [], []
    for row in tx_rpdo[:N]:
        rpdo.on_message(rpdo.cob_id, bytes(row["data"][: row["dlc"]]), 0.0)
        controlword.append(rpdo[0x6040].raw)
        torque.append(rpdo[0x6071].raw)
    for row in rx_tpdo[:N]:
        tpdo.on_message(tpdo.cob_id, bytes(row["data"][: row["dlc"]]), 0.0)
        statusword.append(tpdo[0x6041].raw)
        position.append(tpdo[0x6064].raw)
    np.testing.assert_array_equal(torque, s["dac_counts"][:, 0])
    np.testing.assert_array_equal(position, s["counts"][:, 0])
    assert set(controlword) == {codec.Command.ENABLE_OPERATION.word}
    assert all(codec.decode_state(w) is codec.PowerState.OPERATION_ENABLED for w in statusword)
    design = Design.from_json(data.attachments["design.json"].decode())
    assert design.input_delay_samples == 1 and design.Phi.shape == (3, 3)


def test_the_run_ends_with_zero_torque_disable_shutdown_then_the_syncs_stop(
    step_cia402: Config, tmp_path: Path
) -> None:
    data = _run(step_cia402, tmp_path / "run.mcap", duration_s=0.05)
    f = data.frames
    tx = f[f["direction"] == 1]
    tail = [(int(r["arbitration_id"]), bytes(r["data"][: r["dlc"]])) for r in tx[-7:]]
    assert tail == [
        (0x201, bytes.fromhex("0f000000")), (0x080, b""),
        (0x201, bytes.fromhex("07000000")), (0x080, b""),
        (0x201, bytes.fromhex("06000000")), (0x080, b""),
        (0x000, b"\x80\x01"),
    ]  # fmt: skip
    assert data.truth["applied_current_a"][-1, 0] == 0.0


@pytest.mark.parametrize("name", ["paper-step", "paper-sine"])
def test_tracks_like_native_and_the_dob_still_halves_the_error(name: str, tmp_path: Path) -> None:
    native = _tracking_error_rms(_run(load_config(scenario_path(name)), tmp_path / "native.mcap"))
    cia402 = load_config(scenario_path(f"{name}-cia402"))
    on = _tracking_error_rms(_run(cia402, tmp_path / "on.mcap", dob_enabled=True))
    off = _tracking_error_rms(_run(cia402, tmp_path / "off.mcap", dob_enabled=False))
    assert on <= 1.15 * native, (on, native)
    assert on <= 0.5 * off, (on, off)


def test_the_scenario_gains_are_the_papers_augmented_for_the_delay(step_cia402: Config) -> None:
    Phi0, Gam0 = zoh(step_cia402.plant.A, step_cia402.plant.B, step_cia402.plant.period_ns)
    Kc = np.array([[107.42, 0.3]])
    np.testing.assert_allclose(step_cia402.design.feedback.Kc, np.hstack([Kc @ Phi0, Kc @ Gam0]), rtol=1e-12)
    design = Design.from_json(
        _design_json(step_cia402)
    )  # the closed loop: the paper's eigenvalues plus one at 0
    Phi0_cl = np.linalg.eigvals(Phi0 - Gam0 @ Kc)
    aug_cl = np.linalg.eigvals(design.Phi - design.Gam @ design.Kc)
    np.testing.assert_allclose(np.sort_complex(aug_cl), np.sort_complex(np.append(Phi0_cl, 0.0)), atol=1e-9)


def _design_json(config: Config) -> str:
    from dob_hil.design import build_design

    return build_design(config).to_json()


def test_a_drive_fault_ends_the_run_with_its_emcy_code(step_cia402: Config, tmp_path: Path) -> None:
    text = scenario_path("paper-step-cia402").read_text() + "\n[sim.faults]\nfault_at_s = 0.3\n"
    config = parse_config_text(text)
    with pytest.raises(DriveFault, match="0x2310"):
        run_session(config, RunOptions(log_path=tmp_path / "fault.mcap"))
    data = read_log(tmp_path / "fault.mcap")
    reason = data.metadata["summary"]["exit_reason"]
    assert reason.startswith("drive fault:") and "EMCY 0x2310" in reason
    assert 990 <= len(data.samples) <= 1010  # ended at the fault (0.3 s = period 1000)
    assert np.abs(data.samples["dac_counts"]).max() <= LIMIT_CODE


def test_lockstep_is_deterministic(tmp_path: Path) -> None:
    config = load_config(scenario_path("paper-sine-cia402"))
    a = _run(config, tmp_path / "a.mcap", duration_s=0.2).samples
    b = _run(config, tmp_path / "b.mcap", duration_s=0.2).samples
    for name in ("counts", "x_hat", "x_bar", "u_cmd_a", "dac_counts"):
        np.testing.assert_array_equal(a[name], b[name])


def test_cli_runs_the_scenario(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "cli.mcap"
    rc = main(
        ["run", "--scenario", "paper-step-cia402", "--duration", "0.1", "--log", str(log), "--no-progress"]
    )
    assert rc == 0
    assert "completed" in capsys.readouterr().out
    assert len(read_log(log).samples) == 333


def test_lockstep_configuration_runs_in_one_thread_and_repeats_frame_for_frame(
    step_cia402: Config, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each SDO request is answered by servicing the drive in the caller's thread (no pump thread):
    two runs log the same frames in the same order, each SDO answer right after its request."""
    started: list[str] = []
    real_start = threading.Thread.start

    def spy_start(self: threading.Thread) -> None:
        started.append(self.name)
        real_start(self)

    monkeypatch.setattr(threading.Thread, "start", spy_start)
    runs = [_run(step_cia402, tmp_path / f"run{i}.mcap", duration_s=0.003) for i in range(2)]
    assert not [name for name in started if name.startswith("cia402-config")]
    first, second = (r.frames for r in runs)
    assert len(first) == len(second) > 50
    for field in ("timestamp_ns", "arbitration_id", "direction", "dlc", "data"):
        np.testing.assert_array_equal(first[field], second[field])
    sdo_rx, sdo_tx = 0x600 + NODE, 0x580 + NODE
    ids = list(first["arbitration_id"])
    requests = [i for i, aid in enumerate(ids) if aid == sdo_rx]
    assert len(requests) > 40
    assert all(ids[i + 1] == sdo_tx for i in requests)  # the answer follows its request at once


def test_a_drive_failing_during_lockstep_configuration_is_a_drive_fault(
    step_cia402: Config, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The drive is serviced inside canopen's send: its error comes out as one DriveFault (the
    CLI's one line), not as the raw exception."""
    from firmware_sim.cia402.lockstep import Cia402Lockstep

    calls = [0]
    real = Cia402Lockstep.service

    def failing(self: Cia402Lockstep) -> int:
        calls[0] += 1
        if calls[0] == 10:
            raise RuntimeError("drive blew up")
        return real(self)

    monkeypatch.setattr(Cia402Lockstep, "service", failing)
    with pytest.raises(DriveFault, match="drive blew up"):
        run_session(step_cia402, RunOptions(log_path=tmp_path / "fail.mcap", duration_s=0.01))
