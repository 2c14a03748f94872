"""The pacer learns how late its sleep wakes and spins only that stretch (controllers/runtime/pacing.py)."""

from __future__ import annotations

import pytest

from drivectl.controllers.runtime.pacing import Pacer


class _OvershootClock:
    """Simulated time: a sleep wakes ``over`` late; each reading passes 1 us (so a spin ends); spun time is
    counted."""

    def __init__(self, over: float) -> None:
        self.t, self.over, self.spun = 0.0, over, 0.0

    def now(self) -> float:
        self.t += 1e-6
        self.spun += 1e-6
        return self.t

    def sleep(self, s: float) -> None:
        self.t += s + self.over


def _run(over: float, cycles: int = 3000) -> tuple[Pacer, _OvershootClock, list[float]]:
    clock = _OvershootClock(over)
    pacer = Pacer(0.001, now=clock.now, sleep=clock.sleep)
    late = [pacer.wait(k) for k in range(1, cycles + 1)]
    return pacer, clock, late


def test_a_punctual_sleep_is_spun_for_little_and_every_cycle_starts_on_time():
    pacer, clock, late = _run(30e-6)
    # learned down from 300 us to SPIN_GAIN x 30 us within the run; the cycles stay punctual throughout
    assert pacer.spin_s == pytest.approx(Pacer.SPIN_GAIN * 30e-6, abs=2e-6)
    assert max(late) < 2e-6 and pacer.missed == 0
    # the last second spun ~45 us a cycle, not 300
    clock.spun = 0.0
    late = [pacer.wait(k) for k in range(3001, 4001)]
    assert clock.spun / 1000 < 60e-6 and max(late) < 2e-6


def test_a_late_sleep_widens_the_spin_up_to_its_bound_and_the_lateness_is_what_is_left():
    pacer, _, late = _run(500e-6)
    assert pacer.spin_s == Pacer.SPIN_MAX_S
    # a sleep 500 us late against a 300 us spin: each cycle 200 us late, none missed (half a cycle is 500 us)
    assert late[-1] == pytest.approx(200e-6, abs=3e-6) and pacer.missed == 0


def test_one_late_wake_up_widens_the_spin_then_it_decays():
    clock = _OvershootClock(30e-6)
    pacer = Pacer(0.001, now=clock.now, sleep=clock.sleep)
    for k in range(1, 3001):
        pacer.wait(k)
    clock.over = 150e-6
    pacer.wait(3001)
    assert pacer.spin_s == pytest.approx(Pacer.SPIN_GAIN * 150e-6, rel=0.02)
    clock.over = 30e-6
    for k in range(3002, 6002):
        pacer.wait(k)
    assert pacer.spin_s < 60e-6
