"""What the EMPS records can show: the gap profiles behind explain's two EMPS misses (docs/explain.md,
"The EMPS cases").

1. offset: on the estimation record against the reference model *without* its offset, the gap for a given
   offset with the direction-dependent viscous friction refitted (scale, scale_neg) at each: where the
   record wants the offset once that friction is in;
2. timing: the gap of the best model (that friction and offset refitted on the record) against an extra
   shift of the effort (negative: the effort advanced in memory, forces earlier than the file's
   alignment), on both halves of the estimation record and on the validation record (taken 15 days later);
3. the same timing profile on a synthetic replica: the best model in closed loop under the rig's own PD
   law (its velocity filter regressed from the record), the record's reference, 50 nm quantisation and
   2 N white force noise: where the method puts the least gap when the timing is known to be right.

4. with ``--explain``: explain itself on replicas, where the truth is known: the replica (nothing missing),
   the replica advanced 1 ms, and a replica of the benchmark's symmetric model (its +3.1648 N offset a
   real constant force) against the reference without its offset.

    python bench/explain_emps_profile.py [--json] [--explain]

Reads the records where they are ($DRIVECTL_EMPS_DIR or shared/real/emps in a parent); never copies them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from explain_traces import EMPS_REFERENCE, advance_effort, emps_dir  # noqa: E402

from drivectl.plant_emulator.models import PlantSpec  # noqa: E402
from drivectl.tools.explain.data import gaps_of, prepare  # noqa: E402
from drivectl.tools.explain.fit import Fit, refine_jointly  # noqa: E402
from drivectl.tracefile.format import Trace  # noqa: E402

OFFSETS = (-1.0, 0.0, 0.25, 0.5, 1.0, 2.0, 3.1648)
SHIFTS_MS = (-1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5)
#: the rig's PD law (the file's header): vir = kv (kp (qg - qm) - dqf)
GTAU, KP, KV = 35.15065188248547, 160.18, 243.45


def _nominal() -> PlantSpec:
    return PlantSpec("emps-reference", "rigid", "N", dict(EMPS_REFERENCE))


def _viscous(scale: float = 0.82, scale_neg: float = 1.19) -> Fit:
    return Fit("viscous", {"scale": scale, "scale_neg": scale_neg}, 0.0, key="viscous+-")


def _cut(tr: Trace, sl: slice, advance: int = 0) -> Trace:
    cols = {k: np.asarray(v)[sl] for k, v in tr.columns.items()}
    cols["effort"] = advance_effort(cols["effort"], advance)
    return Trace(cols, dict(tr.meta))


def offset_profile(tr: Trace) -> list[dict[str, float]]:
    nom = _nominal()
    prep = prepare(tr, nom)
    out = []
    for force in OFFSETS:
        spec = nom.with_effect("offset", force=force) if force else nom
        fit = refine_jointly(prep.on(spec), spec, [_viscous()], iterations=8)[0]
        out.append({"offset_N": force, "gap_um": fit.gap * 1e6, "c_pos": fit.params["scale"] * EMPS_REFERENCE["c_pos"],
                    "c_neg": fit.params["scale_neg"] * EMPS_REFERENCE["c_neg"]})
    return out


def _best_model(tr: Trace) -> tuple[PlantSpec, dict[str, float]]:
    nom = _nominal()
    fits = refine_jointly(prepare(tr, nom), nom, [_viscous(), Fit("offset", {"force": 0.25}, 0.0)], iterations=8)
    spec = nom
    for f in fits:
        spec = f.add_to(spec)
    return spec, {"scale": fits[0].params["scale"], "scale_neg": fits[0].params["scale_neg"],
                  "offset_N": fits[1].params["force"], "gap_um": fits[0].gap * 1e6}


def timing_profile(tr: Trace, spec: PlantSpec) -> dict[str, float]:
    """Gap (um) per extra shift (ms) of the effort: advanced 1 row, then delayed 0..1.5 ms."""
    prep = prepare(_cut(tr, slice(None), advance=1), spec)
    delays = [s + 1.0 for s in SHIFTS_MS]
    gaps = gaps_of(prep, [spec.with_effect("delay", delay=d * 1e-3) if d > 0 else spec for d in delays])
    return {f"{s:+.2f}": float(g) * 1e6 for s, g in zip(SHIFTS_MS, gaps, strict=True)}


def synthetic_replica(asrecorded: Trace, spec: PlantSpec, seed: int = 1, force_noise: float = 2.0) -> Trace:
    t = np.asarray(asrecorded.columns["time_s"])
    qg = np.asarray(asrecorded.columns["ref_m"])
    qm = np.asarray(asrecorded.columns["pos_m"])
    vir = np.asarray(asrecorded.columns["effort"]) / GTAU
    # the velocity filter dqf as a linear filter of the last 8 positions, regressed from the record
    dq = -(vir - KV * KP * (qg - qm)) / KV
    taps = 8
    X = np.column_stack([qm[taps - j:len(qm) - j] for j in range(taps)])
    b, *_ = np.linalg.lstsq(X, dq[taps:], rcond=None)
    b -= b.mean()  # a derivative: no gain at standstill
    plant = spec.build(float(np.median(np.diff(t))))
    rng = np.random.default_rng(seed)
    state = plant.initial_state(float(qm[0]))
    hist = np.full(taps, float(qm[0]))
    pos, eff = np.zeros(len(t)), np.zeros(len(t))
    for k in range(len(t)):
        q = round(plant.position(state) / 50e-9) * 50e-9
        pos[k] = q
        hist = np.roll(hist, 1)
        hist[0] = q
        eff[k] = GTAU * KV * (KP * (qg[k] - q) - float(b @ hist))
        state = plant.step(state, eff[k] + force_noise * rng.standard_normal())  # applied in the cycle computed
    # the train file's alignment: row k carries the force that acts from t(k+1)
    return Trace({"time_s": t, "ref_m": qg, "pos_m": pos, "effort": np.concatenate((eff[1:], eff[-1:]))},
                 {"effort_unit": "N", "dt_s": "0.001"})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--explain", action="store_true", help="also run explain on the replicas (~1 min)")
    args = ap.parse_args()
    d = emps_dir()
    if d is None:
        print("EMPS records absent (set DRIVECTL_EMPS_DIR)", file=sys.stderr)
        return 2
    train = Trace.read(d / "emps-train.csv")
    n = len(train.columns["time_s"])
    out: dict = {"offset_profile": offset_profile(train), "timing": {}}
    records = (("train 0-12.4 s", _cut(train, slice(0, n // 2))),
               ("train 12.4-24.8 s", _cut(train, slice(n // 2, None))), ("pulses", Trace.read(d / "emps-pulses.csv")))
    for name, tr in records:
        spec, model = _best_model(tr)
        out["timing"][name] = {"model": model, "gap_um_by_shift_ms": timing_profile(tr, spec)}
    spec, model = _best_model(train)
    replica = synthetic_replica(Trace.read(d / "emps-train-asrecorded.csv"), spec)
    out["timing"]["synthetic replica"] = {"model": model, "gap_um_by_shift_ms": timing_profile(replica, spec)}
    if args.explain:
        from explain_traces import emps_plant

        from drivectl.tools.explain.core import explain

        symmetric = synthetic_replica(Trace.read(d / "emps-train-asrecorded.csv"), emps_plant())
        runs = (("replica", replica, spec), ("replica advanced 1 ms", _cut(replica, slice(None), advance=1), spec),
                ("symmetric replica, offset left out", symmetric, _nominal()))
        out["replica_explain"] = {}
        for name, tr, model_spec in runs:
            res = explain(tr, model_spec)
            effects = [{"effect": e["effect"], "params": e["params"]} for e in res.effects]
            out["replica_explain"][name] = {"effects": effects, "gap_before_um": res.gap_before * 1e6,
                                            "gap_after_um": res.gap_after * 1e6, "floor_um": res.floor * 1e6}
    if args.json:
        print(json.dumps(out))
        return 0
    print("offset (N)  gap um  c+ N s/m  c- N s/m   (estimation record, direction-dependent viscous refitted)")
    for r in out["offset_profile"]:
        print(f"{r['offset_N']:9.4g}  {r['gap_um']:6.2f}  {r['c_pos']:8.1f}  {r['c_neg']:8.1f}")
    print("\ngap um against an extra shift of the effort (ms; negative = forces earlier), best model of each record")
    print(f"{'record':20s}" + "".join(f"{s:>8s}" for s in out["timing"]["pulses"]["gap_um_by_shift_ms"]))
    for name, r in out["timing"].items():
        print(f"{name:20s}" + "".join(f"{g:8.2f}" for g in r["gap_um_by_shift_ms"].values()))
    for name, r in out.get("replica_explain", {}).items():
        named = ", ".join(f"{e['effect']} " + " ".join(f"{k}={v:.4g}" for k, v in e["params"].items())
                          for e in r["effects"]) or "none"
        print(f"explain, {name}: {named}; gap {r['gap_before_um']:.1f} -> {r['gap_after_um']:.1f} um "
              f"(floor {r['floor_um']:.1f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
