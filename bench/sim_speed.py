"""Simulation speed: real-time factor of one SimAxis run and of a batch of gain sets.

* single: `two-mass` + PID-NFTSM on the seed-000 scenario (2.5 s at 1 kHz) through SimAxis and the
  servo loop, exactly as `drivectl trace --axis z` runs it; plain Python. Target >= 100x.
* batch: 1000 PID-NFTSM gain sets (Kp, Ki, Kd, rho1, m~ drawn around the paper's) on the same
  scenario, simulated together by plant_emulator.batch (numpy over the batch axis, the same
  controller code with array gains). Aggregate axis-seconds per wall second. Target >= 10 000x.

Wall-clock figures are noisy on a shared machine: each is the best of ``--repeat`` runs, and the
table also shows the median.

    python bench/sim_speed.py [--json] [--repeat 5] [--members 1000]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from drivectl.controllers.pid_nftsm import TdePidNftsm
from drivectl.controllers.runtime.servo import run
from drivectl.machine.config import load_config
from drivectl.plant_emulator.batch import run_batch
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.profiles.library import load_profile

DT = 0.001


def single_run_seconds() -> tuple[float, float]:
    z = load_config().axis("z")  # the embedded machine's axis z: two-mass + PID-NFTSM on seed-000
    spec = load_plant(z.plant)
    profile = load_profile(z.profile, axis="z")
    axis = SimAxis(spec.build(DT), name="z", initial_position=profile.start_position)
    controller = TdePidNftsm(DT, z.controller_settings)
    t0 = time.perf_counter()
    res = run(axis, controller, profile)
    wall = time.perf_counter() - t0
    return wall, float(res.trace.time[-1])


def batch_seconds(members: int, seed: int = 0) -> tuple[float, float, int]:
    rng = np.random.default_rng(seed)
    defaults = TdePidNftsm(DT, load_config().axis("z").controller_settings).settings

    def around(value: float, spread: float) -> np.ndarray:
        return value * np.exp(rng.uniform(-spread, spread, members))

    controller = TdePidNftsm(
        DT,
        kp=around(defaults.kp, 0.5),
        ki=around(defaults.ki, 0.5),
        kd=around(defaults.kd, 0.3),
        rho1=around(defaults.rho1, 0.5),
        m_tilde=around(defaults.m_tilde, 0.2),
        accel_filter_hz=defaults.accel_filter_hz,
    )
    spec = load_plant("two-mass")
    profile = load_profile("seed-000", axis="z")
    t0 = time.perf_counter()
    with np.errstate(all="ignore"):  # unstable members blow up; they are counted, not timed apart
        res = run_batch(spec.build(DT), controller, profile, members, resolution=76.29e-9)
    wall = time.perf_counter() - t0
    return wall, (res.cycles - 1) * DT * members, int(res.finite.sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--members", type=int, default=1000)
    args = ap.parse_args()

    singles = [single_run_seconds() for _ in range(args.repeat)]
    sim_s = singles[0][1]
    walls = [w for w, _ in singles]
    batches = [batch_seconds(args.members) for _ in range(max(1, args.repeat // 2))]
    bwalls = [w for w, _, _ in batches]
    axis_seconds, stable = batches[0][1], batches[0][2]
    single_rtf = sim_s / min(walls)
    batch_rtf = axis_seconds / min(bwalls)
    if args.json:
        print(json.dumps({"single_rtf": round(single_rtf, 1), "batch_rtf": round(batch_rtf, 1)}))
        return
    print(f"{'run':<34} {'simulated':>12} {'wall best':>10} {'wall median':>12} {'RTF':>10} {'target':>8}")
    print(f"{'single: two-mass + PID-NFTSM':<34} {sim_s:>10.2f} s {min(walls):>9.4f}s "
          f"{statistics.median(walls):>11.4f}s {single_rtf:>9.0f}x {'100x':>8}")
    print(f"{f'batch: {args.members} gain sets':<34} {axis_seconds:>10.0f} s {min(bwalls):>9.4f}s "
          f"{statistics.median(bwalls):>11.4f}s {batch_rtf:>9.0f}x {'10000x':>8}")
    print(f"\nbatch members that stayed finite: {stable}/{args.members} (gains drawn log-uniformly around the "
          "paper's; unstable ones still cost the same time)")


if __name__ == "__main__":
    main()
