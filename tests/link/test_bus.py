"""open_bus: python-can configuration honoured, failures turned into errors a user can act on."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Any

import can
import can.util
import pytest
from can.interfaces.virtual import VirtualBus

from dob_hil.errors import ConfigError, DriveFault
from dob_hil.link.bus import open_bus

from .conftest import unique_channel
from .test_back2back import socketcan_unavailable


@pytest.fixture
def no_can_config(monkeypatch: pytest.MonkeyPatch) -> None:
    """Isolate from the user's python-can config files and environment."""
    monkeypatch.setattr(can.util, "CONFIG_FILES", [])
    monkeypatch.setattr(can, "rc", {})
    for name in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(name, raising=False)


def test_explicit_values(no_can_config: None) -> None:
    channel = unique_channel()
    with open_bus("virtual", channel, 500_000) as bus:
        assert isinstance(bus, VirtualBus)
        assert channel in bus.channel_info


def test_environment_is_honoured(no_can_config: None, monkeypatch: pytest.MonkeyPatch) -> None:
    channel = unique_channel()
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", channel)
    with open_bus(None, None, None) as bus:
        assert channel in bus.channel_info


def test_config_file_is_honoured(
    no_can_config: None, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    channel = unique_channel()
    rc = tmp_path / "canrc"
    rc.write_text(f"[default]\ninterface = virtual\nchannel = {channel}\n")
    monkeypatch.setattr(can.util, "CONFIG_FILES", [str(rc)])
    with open_bus() as bus:
        assert channel in bus.channel_info
    with open_bus(channel=channel + "-given") as bus:  # a given value wins over the file
        assert channel + "-given" in bus.channel_info


def test_receive_own_messages_is_passed_on(no_can_config: None) -> None:
    with open_bus("virtual", unique_channel(), receive_own_messages=True) as bus:
        bus.send(can.Message(arbitration_id=0x201, is_extended_id=False, data=b"\x00\x00\x00"))
        assert bus.recv(1.0) is not None
    with open_bus("virtual", unique_channel()) as bus:
        bus.send(can.Message(arbitration_id=0x201, is_extended_id=False, data=b"\x00\x00\x00"))
        assert bus.recv(0.0) is None


def test_no_interface_anywhere(no_can_config: None) -> None:
    with pytest.raises(ConfigError) as info:
        open_bus()
    assert info.value.field == "interface"
    assert "no CAN interface given and none configured" in str(info.value)
    assert "CAN_INTERFACE" in str(info.value)


def test_unknown_interface(no_can_config: None) -> None:
    with pytest.raises(
        ConfigError, match=r'interface: Unknown interface type "nosuchcan"; known interfaces: .*virtual'
    ):
        open_bus("nosuchcan", "x")


def test_bad_bitrate() -> None:
    with pytest.raises(ConfigError, match="bitrate: must be a positive integer in bit/s, got -5"):
        open_bus("virtual", "x", -5)


@pytest.mark.skipif(socketcan_unavailable() is None, reason="SocketCAN is available here; nothing to refuse")
def test_no_socketcan_support_is_a_clear_drive_fault(no_can_config: None) -> None:
    with pytest.raises(DriveFault) as info:
        open_bus("socketcan", "vcan0")
    text = str(info.value)
    assert "interface 'socketcan' channel 'vcan0'" in text
    assert "no SocketCAN support" in text and f"errno {errno.EAFNOSUPPORT}" in text


@pytest.mark.parametrize(
    ("raised", "error", "needle"),
    [
        (
            TypeError("slcanBus.__init__() missing 1 required positional argument: 'channel'"),
            ConfigError,
            "needs a channel",
        ),
        (OSError(errno.ENODEV, "No such device"), DriveFault, "no such CAN device 'can7'"),
        (OSError(errno.EPERM, "Operation not permitted"), DriveFault, "permission denied"),
        (can.CanInitializationError("device busy"), DriveFault, "device busy"),
        (can.CanInterfaceNotImplementedError("Cannot import module x"), DriveFault, "Cannot import module x"),
        (NameError("name 'canGetNumberOfChannels' is not defined"), DriveFault, "NameError"),
    ],
)
def test_backend_failures_are_mapped(
    monkeypatch: pytest.MonkeyPatch, raised: Exception, error: type[Exception], needle: str
) -> None:
    def failing_bus(*args: Any, **kwargs: Any) -> can.BusABC:
        raise raised

    monkeypatch.setattr(can, "Bus", failing_bus)
    with pytest.raises(error, match=needle) as info:
        open_bus("socketcan", "can7")
    assert info.value.__cause__ is raised
