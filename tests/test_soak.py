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


def test_the_wall_soak_lays_a_fault_at_a_host_stop_only_when_cyclictest_saw_one_around_it():
    """bench/soak.py --cyclictest: each spike read once (cyclictest prints them as they come and again at its
    end), and a fault counted as the host's only during a stop or just after it ended."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import soak

    out = ("# /dev/cpu_dma_latency set to 0us\n"
           "T: 1 Spike:   29393: TS:   1996530138\n"
           "T: 0 (15613) P:49 I:1000 C:1867807 Min:      6 Act:   29 Avg:   36 Max:   32464\n"
           "T: 1 Spike:   29393: TS:   1996530138\n"
           "T: 0 Spike:   12000: TS:   2000100000\n")
    spikes = soak.cyclictest_spikes(out)
    assert [t for t, _, _ in spikes] == [1, 0]
    assert [(round(late, 6), round(ts, 6)) for _, late, ts in spikes] == [(0.029393, 1996.530138), (0.012, 2000.1)]
    woke = 1996.530138
    faults = [woke - 0.020,  # during the stop
              woke + 0.004,  # found just after it ended
              woke + 0.5,  # long after: not the stop's
              woke - 0.040]  # before it began
    assert soak.at_host_stops(faults, spikes) == 2
    line = soak.host_stops_line({"_spikes": spikes, "_fault_at": faults})
    assert "2 wake-up(s) 10 ms late or more (worst 29.4 ms)" in line and line.endswith("faults at one: 2 of 4")
    failed = soak.host_stops_line({"_spikes": [], "_fault_at": [],
                                   "_cyclictest_error": "Unable to change scheduling policy!"})
    assert "cyclictest failed: Unable to change" in failed
