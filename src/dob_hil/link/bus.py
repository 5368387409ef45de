"""Opening a python-can bus with errors a user can act on.

:func:`open_bus` is ``can.Bus(...)`` with only the values given: whatever is omitted (None) comes
from python-can's own configuration, in its order: ``can.rc``, the environment (``CAN_INTERFACE``,
``CAN_CHANNEL``, ``CAN_BITRATE``, ``CAN_CONFIG``) and the config files ``~/can.conf``, ``/etc/can.conf``,
``~/.can``, ``~/.canrc`` on Linux (``[default]`` section, or the ``context`` section). Failures become
:class:`~dob_hil.errors.ConfigError` (the user named something that does not exist: an unknown
interface, no interface at all, a missing channel) or :class:`~dob_hil.errors.DriveFault` (the
host cannot open it: no SocketCAN in the kernel, no such device, a vendor library missing).

Own frames. ``receive_own_messages`` is passed to the interface (default False). ``udp_multicast``
delivers every process its own frames anyway (multicast loopback); that is harmless for
:class:`~dob_hil.link.native.NativeDriveLink`, which filters by id and silently skips its own
COMMAND and CONTROL ids (counted in ``stats.own_echoes``), but the log then holds each sent frame
twice (once as tx, once as rx).
"""

from __future__ import annotations

import errno
from typing import Any

import can

from dob_hil.errors import ConfigError, DriveFault


def open_bus(
    interface: str | None = None,
    channel: str | None = None,
    bitrate: int | None = None,
    *,
    receive_own_messages: bool = False,
    context: str | None = None,
    **kwargs: Any,
) -> can.BusABC:
    """A python-can bus; omitted values come from python-can's config files and environment.

    ``kwargs`` are interface-specific options passed to ``can.Bus`` unchanged (e.g.
    ``fd=False`` or ``tx_queue_len``); ``context`` selects a config-file section.
    """
    if bitrate is not None and (isinstance(bitrate, bool) or not isinstance(bitrate, int) or bitrate <= 0):
        raise ConfigError("bitrate", f"must be a positive integer in bit/s, got {bitrate!r}")
    options: dict[str, Any] = dict(kwargs)
    if bitrate is not None:
        options["bitrate"] = bitrate
    options["receive_own_messages"] = receive_own_messages
    where = _where(interface, channel)
    try:
        return can.Bus(channel=channel, interface=interface, config_context=context, **options)
    except can.CanInterfaceNotImplementedError as exc:
        raise _interface_error(interface, where, exc) from exc
    except NotImplementedError as exc:  # python-can's "CAN interface ... not supported"
        raise ConfigError("interface", f"{exc}; known interfaces: {_known()}") from exc
    except TypeError as exc:
        if "channel" in str(exc):
            raise ConfigError(
                "channel", f"{where}: this interface needs a channel (-c/--channel or CAN_CHANNEL)"
            ) from exc
        raise DriveFault(f"cannot open CAN bus {where}: {exc}") from exc
    except OSError as exc:
        raise DriveFault(_os_error_text(interface, channel, where, exc)) from exc
    except ValueError as exc:  # python-can: no channel could be determined, or a bad option value
        field = "channel" if "channel" in str(exc).lower() else "bus options"
        raise ConfigError(field, f"cannot open CAN bus {where}: {exc}") from exc
    except can.CanError as exc:
        raise DriveFault(f"cannot open CAN bus {where}: {exc}") from exc
    except Exception as exc:  # a backend failing in its own way (e.g. a vendor library missing)
        raise DriveFault(f"cannot open CAN bus {where}: {type(exc).__name__}: {exc}") from exc


def _where(interface: str | None, channel: str | None) -> str:
    iface = interface if interface is not None else "<from python-can config>"
    chan = channel if channel is not None else "<default>"
    return f"interface {iface!r} channel {chan!r}"


def _known() -> str:
    return ", ".join(sorted(can.VALID_INTERFACES))


def _interface_error(interface: str | None, where: str, exc: Exception) -> Exception:
    text = str(exc)
    if "Unknown interface type" in text:
        if interface is None and '"None"' in text:
            return ConfigError(
                "interface",
                "no CAN interface given and none configured: pass -i/--interface, set CAN_INTERFACE, "
                f"or write one into ~/.canrc; known interfaces: {_known()}",
            )
        return ConfigError("interface", f"{text}; known interfaces: {_known()}")
    return DriveFault(f"cannot use CAN bus {where}: {text}")


def _os_error_text(interface: str | None, channel: str | None, where: str, exc: OSError) -> str:
    if exc.errno == errno.EAFNOSUPPORT:
        return (
            f"cannot open CAN bus {where}: this host has no SocketCAN support "
            f"(socket(AF_CAN) fails with errno {exc.errno}, {exc.strerror}); load the can and vcan "
            "kernel modules, or use interface 'virtual' or 'udp_multicast'"
        )
    if exc.errno in (errno.ENODEV, errno.ENXIO):
        return (
            f"cannot open CAN bus {where}: no such CAN device {channel!r} "
            f"(errno {exc.errno}, {exc.strerror}); check `ip link show` and that it is up"
        )
    if exc.errno in (errno.EPERM, errno.EACCES):
        return f"cannot open CAN bus {where}: permission denied (errno {exc.errno}, {exc.strerror})"
    return f"cannot open CAN bus {where}: {exc}"
