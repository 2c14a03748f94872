"""Issue 7 point 9, the short version of bench/soak.py (which runs 10 simulated minutes): two axes
in lockstep, random faults, recoveries and re-enables; every fault found in the traces, memory flat,
no hang (faulthandler guard)."""

from __future__ import annotations

from drivectl.tools.conformance.soak import SOAK_FAULTS, run_soak


def test_short_soak_accounts_for_every_fault(tmp_path):
    r = run_soak(15.0, seed=3, hang_guard_s=60.0, out_dir=tmp_path)
    assert r.simulated_s >= 15.0 and r.moves >= 15
    assert not r.unaccounted, r.unaccounted
    assert r.all_accounted and sum(r.injected.values()) >= 10
    assert len(r.injected) >= 6  # a spread of kinds, not one fault ten times
    assert set(r.injected) <= set(SOAK_FAULTS)
    assert r.recoveries >= 5
    # tracemalloc (after a full collection) from the warm-up to the end: the samples scatter by
    # +-50 KiB (what one move holds at the moment); a leak per move would show as hundreds
    assert len(r.memory_samples) >= 10
    assert r.memory_growth_kib < 256, r.memory_samples
