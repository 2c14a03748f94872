"""SDO transfers of one node as a bus log shows them (CiA 301 7.2.4): expedited and segmented, joined.

A transfer is an exchange of frames between the client (COB-ID 0x600 + node) and the server (0x580 + node);
:meth:`SdoTracker.feed` takes them in log order and returns a :class:`Transfer` when one completes (the
server confirmed a download, or sent the last segment of an upload) or is aborted. A write counts only once the
server confirmed it: the PDO configuration replayed from a log (tools/buslog/mapping.py) is what the drive
took, not what the master asked. Block transfers are reported as such, not joined.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass


@dataclass(frozen=True)
class Transfer:
    t: float  # the timestamp of the frame that completed it
    kind: str  # "write", "read", "abort", "request" (a request seen, its outcome still open), "block"
    index: int
    sub: int
    value: bytes = b""  # the data written or read
    segmented: bool = False
    abort_code: int = 0
    by_client: bool = False  # an abort sent by the client


class SdoTracker:
    """The SDO exchanges of one node (see the module docstring)."""

    def __init__(self) -> None:
        self._open: dict | None = None  # the transfer in progress

    def feed(self, t: float, request: bool, data: bytes) -> Transfer | None:
        if len(data) != 8:
            return None
        cmd = data[0]
        cs = cmd >> 5
        index, sub = struct.unpack_from("<HB", data, 1)
        if cmd == 0x80:  # abort, either side
            code = struct.unpack_from("<I", data, 4)[0]
            self._open = None
            return Transfer(t, "abort", index, sub, abort_code=code, by_client=request)
        op = self._open
        if request:
            if cs == 1:  # initiate download
                if cmd & 0x02:  # expedited
                    size = 4 - ((cmd >> 2) & 3) if cmd & 0x01 else 4
                    self._open = {"kind": "write", "index": index, "sub": sub, "data": bytes(data[4 : 4 + size]),
                                  "seg": False, "state": "init"}
                else:
                    self._open = {"kind": "write", "index": index, "sub": sub, "data": b"", "seg": True,
                                  "state": "init"}
                return None
            if cs == 2:  # initiate upload
                self._open = {"kind": "read", "index": index, "sub": sub, "data": b"", "seg": False,
                              "state": "init"}
                return None
            if cs == 0 and op is not None and op["kind"] == "write" and op["seg"]:  # download segment
                n = 7 - ((cmd >> 1) & 7)
                op["data"] += bytes(data[1 : 1 + n])
                op["state"] = "last" if cmd & 0x01 else "seg"
                return None
            if cs == 3 and op is not None and op["kind"] == "read":  # upload segment request
                return None
            if cs in (5, 6):
                self._open = None
                return Transfer(t, "block", index, sub, by_client=True)
            return None
        # the server's answers
        if op is None:
            return None
        if op["kind"] == "write":
            if cs == 3 and op["state"] == "init":  # initiate download response
                if not op["seg"]:
                    self._open = None
                    return Transfer(t, "write", op["index"], op["sub"], op["data"])
                op["state"] = "seg"
                return None
            if cs == 1 and op["seg"] and op["state"] == "last":  # the last segment confirmed
                self._open = None
                return Transfer(t, "write", op["index"], op["sub"], op["data"], segmented=True)
            return None
        if op["kind"] == "read":
            if cs == 2 and op["state"] == "init":  # initiate upload response
                if cmd & 0x02:
                    size = 4 - ((cmd >> 2) & 3) if cmd & 0x01 else 4
                    self._open = None
                    return Transfer(t, "read", op["index"], op["sub"], bytes(data[4 : 4 + size]))
                op["seg"], op["state"] = True, "seg"
                return None
            if cs == 0 and op["state"] == "seg":  # an upload segment
                n = 7 - ((cmd >> 1) & 7)
                op["data"] += bytes(data[1 : 1 + n])
                if cmd & 0x01:
                    self._open = None
                    return Transfer(t, "read", op["index"], op["sub"], op["data"], segmented=True)
                return None
            if cs == 6:
                self._open = None
                return Transfer(t, "block", op["index"], op["sub"])
        return None
