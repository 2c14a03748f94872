"""Waits in the waiter's running time (driver/running_time.py), on an injected clock: a stalled waiter does not
blame the peer for its own stall, a silent peer is still given up on."""

from __future__ import annotations

import queue

import pytest

from drivectl.driver.running_time import SLICE_S, RunningTimeSdoClient, get_running, wait_running


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class _Event:
    """Set after ``after`` waits; each wait of ``s`` seconds takes ``s * stretch`` on the clock."""

    def __init__(self, clock: _Clock, after: int | None, stretch: float):
        self.clock, self.after, self.stretch, self.waits = clock, after, stretch, 0

    def is_set(self) -> bool:
        return self.after is not None and self.waits >= self.after

    def wait(self, s: float) -> bool:
        self.waits += 1
        self.clock.t += s * self.stretch
        return self.is_set()


def test_a_stalled_waiter_waits_its_own_running_time_for_the_answer():
    clock = _Clock()
    # every slice overran tenfold (the process, or its VM, was not scheduled): 0.3 s of running time is 15
    # slices, 3 s on the wall clock; the answer that comes at the 12th slice is taken, not timed out
    ev = _Event(clock, after=12, stretch=10.0)
    assert wait_running(ev, 0.3, clock)
    assert clock.t > 0.3 * 5  # on the wall clock far longer than the timeout
    assert ev.waits == 12


def test_a_silent_peer_is_given_up_on_after_the_timeout_of_running_time():
    clock = _Clock()
    ev = _Event(clock, after=None, stretch=1.0)
    assert not wait_running(ev, 0.3, clock)
    assert clock.t == pytest.approx(0.3)
    stalled = _Event(_Clock(), after=None, stretch=10.0)
    assert not wait_running(stalled, 0.3, stalled.clock)
    assert stalled.waits == round(0.3 / SLICE_S)  # bounded: never more slices than the timeout holds


def test_a_wall_limit_bounds_the_wait_but_takes_what_came_during_a_stall():
    clock = _Clock()
    ev = _Event(clock, after=None, stretch=1.0)
    assert not wait_running(ev, 1.0, clock, wall_limit=0.15)  # the peer's watchdog runs on its wall clock
    assert clock.t == pytest.approx(0.16)  # whole slices: the first to end past the limit
    clock = _Clock()
    ev = _Event(clock, after=3, stretch=10.0)  # stalled past the limit: the answer waiting is still taken
    assert wait_running(ev, 1.0, clock, wall_limit=0.15)
    assert ev.waits == 3


class _Queue:
    def __init__(self, clock: _Clock, answer_at: int | None, stretch: float):
        self.clock, self.answer_at, self.stretch, self.gets = clock, answer_at, stretch, 0

    def get(self, timeout: float) -> bytes:
        self.gets += 1
        self.clock.t += timeout * self.stretch
        if self.answer_at is not None and self.gets >= self.answer_at:
            return b"\x60" + bytes(7)
        raise queue.Empty

    def get_nowait(self) -> bytes:
        raise queue.Empty


def test_queue_wait_takes_a_stalled_answer_and_gives_up_on_silence():
    clock = _Clock()
    assert get_running(_Queue(clock, answer_at=14, stretch=20.0), 0.3, clock) == b"\x60" + bytes(7)
    clock = _Clock()
    with pytest.raises(queue.Empty):
        get_running(_Queue(clock, answer_at=None, stretch=1.0), 0.3, clock)
    assert clock.t == pytest.approx(0.3)


def test_sdo_client_reads_a_queued_answer_and_an_abort():
    client = RunningTimeSdoClient(0x601, 0x581, None)
    client.RESPONSE_TIMEOUT = 0.05
    client.on_response(0x581, b"\x60" + bytes(7), 0.0)
    assert client.read_response() == b"\x60" + bytes(7)
    client.on_response(0x581, b"\x80\x00\x10\x00\x00\x00\x02\x06", 0.0)
    from canopen import SdoAbortedError

    with pytest.raises(SdoAbortedError) as exc:
        client.read_response()
    assert exc.value.code == 0x06020000
