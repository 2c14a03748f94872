"""The emulated drive's SDO server: canopen's SdoServer, corrected where CiA 301 says otherwise.

canopen's server is a toolbox (see DESIGN.md, "Known traps"); a drive must also:

* ignore a request that is not 8 bytes or is a remote frame (CiA 301 fixes the SDO frame at 8 bytes;
  CANopenNode drops such a frame the same way, without an abort, as its index is unknown);
* answer nothing outside Pre-operational and Operational (NMT Stopped: only NMT and heartbeat);
* abort a sub-index the object does not have (0x06090011), also on arrays whose entries canopen creates
  on demand, and sub-index 1.. of a plain variable;
* accept an expedited download without size indication (CiA 301: the data are then the object's
  size; canopen took 4 bytes and refused every 16-bit object);
* refuse a block upload or download with 0x05040001 (command specifier not valid): this drive
  supports no block transfer, and canopen's server answered a block upload with an expedited
  response that breaks canopen's own block client;
* abort a segment request with no transfer open (0x05040001) instead of sending an empty segment;
* check every write against the EDS limits (LowLimit/HighLimit: 0x06090032 below, 0x06090031 above)
  before the drive's own rules (reserved values, PDO mapping) see it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

import canopen
from canopen import objectdictionary as odt
from canopen.sdo.constants import (
    EXPEDITED,
    REQUEST_ABORTED,
    REQUEST_BLOCK_DOWNLOAD,
    REQUEST_BLOCK_UPLOAD,
    REQUEST_DOWNLOAD,
    REQUEST_SEGMENT_DOWNLOAD,
    REQUEST_SEGMENT_UPLOAD,
    REQUEST_UPLOAD,
    SDO_STRUCT,
    SIZE_SPECIFIED,
)
from canopen.sdo.server import SdoServer

from drivectl.plant_emulator.frames import FrameGuard

ABORT_COMMAND = 0x05040001  # client/server command specifier not valid or unknown
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
ABORT_TOO_HIGH = 0x06090031
ABORT_TOO_LOW = 0x06090032
ABORT_LENGTH = 0x06070010


def find_object(od: odt.ObjectDictionary, index: int, sub: int) -> odt.ODVariable:
    """The variable at index:sub as the EDS defines it, or the abort CiA 301 prescribes."""
    if index not in od:
        raise canopen.SdoAbortedError(ABORT_NO_OBJECT)
    obj = od[index]
    if isinstance(obj, odt.ODVariable):
        if sub != 0:
            raise canopen.SdoAbortedError(ABORT_NO_SUBINDEX)
        return obj
    if sub not in obj.subindices:  # canopen's ODArray makes up any sub-index asked for
        raise canopen.SdoAbortedError(ABORT_NO_SUBINDEX)
    return obj.subindices[sub]


def check_limits(obj: odt.ODVariable, data: bytes) -> None:
    """The EDS's LowLimit/HighLimit of a numeric object."""
    if obj.data_type not in odt.NUMBER_TYPES or (obj.min is None and obj.max is None):
        return
    value = obj.decode_raw(data)
    if obj.min is not None and value < obj.min:
        raise canopen.SdoAbortedError(ABORT_TOO_LOW)
    if obj.max is not None and value > obj.max:
        raise canopen.SdoAbortedError(ABORT_TOO_HIGH)


class DriveSdoServer(SdoServer):
    """SDO server of one emulated drive; ``serving()`` says whether the NMT state lets it answer,
    ``after_write(index, sub)`` runs once a written value is stored (a new PDO mapping takes effect)."""

    def __init__(self, node: canopen.LocalNode, guard: FrameGuard, serving: Callable[[], bool],
                 after_write: Callable[[int, int], None]):
        super().__init__(0x600 + node.id, 0x580 + node.id, node)
        self.guard = guard
        self.serving = serving
        self.after_write = after_write
        self._open: str | None = None  # "upload" / "download" while a segmented transfer runs
        self._index = 0
        self._subindex = 0

    def on_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 8:
            self.guard.reject("sdo-length", can_id, data, f"SDO request of {len(data)} bytes (CiA 301: 8)")
            return
        if not self.serving():
            return
        ccs = data[0] & 0xE0
        if ccs in (REQUEST_UPLOAD, REQUEST_DOWNLOAD, REQUEST_BLOCK_UPLOAD, REQUEST_BLOCK_DOWNLOAD, REQUEST_ABORTED):
            _, self._index, self._subindex = SDO_STRUCT.unpack_from(data)
        try:
            if ccs == REQUEST_UPLOAD:
                self.init_upload(data)
            elif ccs == REQUEST_SEGMENT_UPLOAD:
                self.segmented_upload(data[0])
            elif ccs == REQUEST_DOWNLOAD:
                self.init_download(data)
            elif ccs == REQUEST_SEGMENT_DOWNLOAD:
                self.segmented_download(data[0], data)
            elif ccs == REQUEST_ABORTED:
                self._open = None  # the client ended the transfer: no answer
            else:  # block transfers (and the unused specifier 7): not supported by this drive
                self._open = None
                self.abort(ABORT_COMMAND)
        except canopen.SdoAbortedError as exc:
            self._open = None
            self.abort(exc.code)

    def init_upload(self, request: bytes) -> None:
        find_object(self.od, self._index, self._subindex)
        self._open = None
        super().init_upload(request)
        if self._buffer:
            self._open = "upload"

    def segmented_upload(self, command: int) -> None:
        if self._open != "upload":
            raise canopen.SdoAbortedError(ABORT_COMMAND)
        super().segmented_upload(command)
        if not self._buffer:
            self._open = None

    def init_download(self, request: bytes) -> None:
        command = request[0]
        obj = find_object(self.od, self._index, self._subindex)
        self._open = None
        if not command & EXPEDITED:
            if not obj.writable:
                raise canopen.SdoAbortedError(0x06010002)
            super().init_download(request)  # segmented: the data follow
            self._open = "download"
            return
        if command & SIZE_SPECIFIED:
            size = 4 - ((command >> 2) & 0x3)
        elif obj.data_type in odt.NUMBER_TYPES:
            size = len(obj) // 8  # CiA 301: no size indicated, the object's own size
        else:
            size = 4
        self._write(obj, bytes(request[4:4 + size]))
        response = bytearray(8)
        SDO_STRUCT.pack_into(response, 0, 0x60, self._index, self._subindex)
        self.send_response(response)

    def segmented_download(self, command: int, request: bytes) -> None:
        if self._open != "download":
            raise canopen.SdoAbortedError(ABORT_COMMAND)
        if command & 0x10 != self._toggle:
            raise canopen.SdoAbortedError(0x05030000)  # toggle bit not alternated
        if command & 0x01:  # last segment: check and store the whole value before the answer
            last = 8 - ((command >> 1) & 0x7)
            data = bytes(self._buffer) + bytes(request[1:last])
            obj = find_object(self.od, self._index, self._subindex)
            self._write(obj, data)
            self._open = None
            response = bytearray(8)
            response[0] = 0x20 | (command & 0x10)
            self.send_response(response)
            return
        super().segmented_download(command, request)

    def _write(self, obj: odt.ODVariable, data: bytes) -> None:
        if not obj.writable:
            raise canopen.SdoAbortedError(0x06010002)
        if obj.data_type in odt.NUMBER_TYPES and len(data) * 8 != len(obj):
            raise canopen.SdoAbortedError(ABORT_LENGTH)
        check_limits(obj, data)
        self._node.set_data(self._index, self._subindex, data, check_writable=True)
        self.after_write(self._index, self._subindex)

    def abort(self, abort_code: int = 0x08000000) -> None:
        self.send_response(struct.pack("<BHBL", 0x80, self._index, self._subindex, abort_code))
