"""Issue 18 point 10, the master's half of the fuzz test: every malformed frame kind, and bounded
random frames, thrown at the master while it runs an axis. Nothing may crash it: each run ends cleanly
(completed) or as a fault with a state the drive reported, the trace whole. (The emulator's half of the
fuzz is the emulator's own test.)

The frames go into the master's receive path only (its network's ``recv``), so the drive runs
untouched and whatever happens is the master's doing."""

from __future__ import annotations

import random

import can
import pytest

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.servo import SAFE_STATES, Channel, StopReason, run_channels
from drivectl.driver.cia402 import PowerState
from drivectl.machine.build import open_machine
from drivectl.machine.config import load_config
from drivectl.profiles.library import load_profile

NODE = 1
#: every malformed kind the master can meet from its drive, the bus, or another node
MALFORMED = [
    (0x180 + NODE, b"\x00\x00", False),  # TPDO1 short
    (0x180 + NODE, bytes(8), False),  # TPDO1 long
    (0x280 + NODE, b"", False),  # TPDO2 empty
    (0x180 + NODE, b"", True),  # TPDO1 as a remote frame
    (0x080 + NODE, b"\x10", False),  # EMCY short (canopen's unpack would raise)
    (0x080 + NODE, bytes(9)[:7], False),  # EMCY 7 bytes
    (0x580 + NODE, b"\x43", False),  # SDO response short
    (0x580 + NODE, b"", True),  # SDO remote frame
    (0x700 + NODE, b"", False),  # heartbeat empty
    (0x700 + NODE, b"\x05\x05", False),  # heartbeat long
    (0x700 + NODE, b"", True),  # node guarding request (RTR): the master answers none
    (0x000, b"\x01", False),  # NMT short
    (0x080, b"\x01\x02", False),  # SYNC with more than its counter
]


class _Fuzz:
    """Wraps the master network's ``recv``: before each real frame, maybe some injected ones."""

    def __init__(self, recv, frames_for_cycle):
        self.recv = recv
        self.frames_for_cycle = frames_for_cycle
        self.pending: list[can.Message] = []
        self.sent = 0

    def __call__(self, timeout):
        if self.pending:
            self.sent += 1
            return self.pending.pop()
        msg = self.recv(timeout)
        if msg is not None and msg.arbitration_id == 0x180 + NODE:  # once a cycle, with its TPDO1
            self.pending = self.frames_for_cycle()
            if self.pending:
                self.pending.append(msg)  # the real one after the injected ones
                self.sent += 1
                return self.pending.pop(0)
        return msg


def _run_fuzzed(frames_for_cycle, duration=0.3):
    cfg = load_config(None)
    ac = cfg.axis("x")
    prof = load_profile("short-move")
    machine = open_machine(cfg, ["x"], start={"x": prof.start_position})
    with machine:
        axis = machine.axes["x"]
        net = axis.network
        fuzz = _Fuzz(net._recv, frames_for_cycle)
        net._recv = fuzz
        ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=machine.specs["x"], axis="x")
        res = run_channels([Channel(axis, ctrl, prof, ac.limits)], duration=duration)
        drive = machine.drives["x"].drive
        return res, drive, fuzz, axis


def _ended_honestly(res, drive):
    n = int(round(0.3 / 0.001)) + 1
    tr = res.trace
    if res.stop is StopReason.COMPLETED:
        assert len(tr) == n
        assert drive.power is not PowerState.OPERATION_ENABLED  # disabled at the end, as always
        return
    f = res.fault
    assert f is not None and len(tr) in (f.cycle, f.cycle + 1)
    if f.safe_after["x"] is not None:  # claimed safe: the drive really is
        assert drive.power in SAFE_STATES and drive.applied == 0.0
    else:
        assert f.safe_state["x"].startswith("may still be powered")


@pytest.mark.parametrize("frame", MALFORMED, ids=[f"0x{c:03X}-{len(d)}{'-rtr' if r else ''}" for c, d, r in MALFORMED])
def test_every_malformed_kind_during_a_run(frame):
    cob, data, remote = frame
    every = 7  # one in every seventh cycle: a lost TPDO now and then, never three in a row
    cycle = [0]

    def frames():
        cycle[0] += 1
        if cycle[0] % every:
            return []
        return [can.Message(arbitration_id=cob, data=data, is_remote_frame=remote, dlc=len(data) or 0)]

    res, drive, fuzz, axis = _run_fuzzed(frames)
    assert res.stop is StopReason.COMPLETED, res.detail
    _ended_honestly(res, drive)
    assert fuzz.sent >= 40
    assert int(res.trace.meta["malformed_frames"]) >= 40  # every one counted


@pytest.mark.parametrize("seed", range(6))
def test_random_frames_during_a_run(seed):
    """Up to 4 random frames a cycle (any COB-ID, length 0-8, data, remote or not), 2000 at most."""
    rng = random.Random(seed)
    budget = [2000]

    def frames():
        out = []
        for _ in range(rng.randint(0, 4)):
            if budget[0] <= 0:
                break
            budget[0] -= 1
            n = rng.randint(0, 8)
            out.append(can.Message(arbitration_id=rng.randrange(0x800), data=bytes(rng.randrange(256) for _ in
                                                                                  range(n)),
                                   is_remote_frame=rng.random() < 0.1, dlc=n))
        return out

    res, drive, fuzz, axis = _run_fuzzed(frames)
    assert fuzz.sent > 0
    _ended_honestly(res, drive)  # completed, or a fault with a state the drive reported


@pytest.mark.parametrize("seed", range(3))
def test_random_frames_on_the_control_cob_ids(seed):
    """Random frames on exactly the COB-IDs the master consumes (TPDOs, EMCY, SDO, heartbeat, SYNC, NMT),
    right lengths mostly: plausible-looking garbage, the hardest kind."""
    rng = random.Random(100 + seed)
    cobs = [0x181, 0x281, 0x081, 0x581, 0x701, 0x080, 0x000]
    sizes = {0x181: 6, 0x281: 6, 0x081: 8, 0x581: 8, 0x701: 1, 0x080: 0, 0x000: 2}

    def frames():
        if rng.random() < 0.7:
            return []
        cob = rng.choice(cobs)
        n = sizes[cob] if rng.random() < 0.8 else rng.randint(0, 8)
        return [can.Message(arbitration_id=cob, data=bytes(rng.randrange(256) for _ in range(n)), dlc=n)]

    res, drive, fuzz, axis = _run_fuzzed(frames)
    _ended_honestly(res, drive)
