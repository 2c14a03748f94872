"""Frame routing for emulated drives: remote frames (RTR) to their handlers, received frames to canopen's
notify (canopen's own notify() carries no RTR bit)."""

from __future__ import annotations

import can
import canopen

from drivectl.driver.network import deliver_remote
from drivectl.plant_emulator.frames import log


def subscribe_remote(network: canopen.Network, can_id: int, callback) -> None:
    """Remote frames (RTR) go to ``network.remote_subscribers`` (canopen's notify() carries no RTR bit:
    a remote frame would look like an empty data frame); the receive loops route them there."""
    subs = network.__dict__.setdefault("remote_subscribers", {})
    if callback not in subs.setdefault(can_id, []):
        subs[can_id].append(callback)


def unsubscribe_remote(network: canopen.Network, can_id: int, callback) -> None:
    subs = network.__dict__.get("remote_subscribers", {})
    if callback in subs.get(can_id, ()):
        subs[can_id].remove(callback)


_handler_errors: set[str] = set()


def deliver(network: canopen.Network, msg: can.Message) -> None:
    """One received frame to the emulated drives on ``network`` (the receive loop of a served emulator):
    a remote frame to the RTR handlers, a data frame to canopen's notify, 29-bit and error frames
    nowhere (not CANopen). A handler that still raises is a bug: logged once per exception type, never
    the end of the emulator."""
    if msg.is_error_frame or msg.is_extended_id:
        return
    try:
        if msg.is_remote_frame:
            deliver_remote(network, msg.arbitration_id)
        else:
            network.notify(msg.arbitration_id, msg.data, msg.timestamp)
    except Exception as exc:  # noqa: BLE001 - the emulator outlives any one frame
        kind = type(exc).__name__
        if kind not in _handler_errors:
            _handler_errors.add(kind)
            log.exception("frame 0x%03X [%s]: handler raised %s (further ones of this type not logged)",
                          msg.arbitration_id, bytes(msg.data).hex(" "), kind)
