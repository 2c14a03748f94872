"""The loop closed on one example (issue 17 point 7): trace on a machine with an effect, explain the
trace, trace again with the model explain wrote, and compare the tracking error before and after.

    python bench/explain_loop.py [--effect stribeck:excess_force=15,velocity=0.002] [--controller mbc]
                                 [--out DIR] [--json]

Every step is the CLI a user runs (drivectl trace --sim, drivectl explain, drivectl trace --model);
the machine is SimAxis with the effect (``--effect`` is the machine's only: the model never carries it).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from drivectl.tools.cli.main import main as drivectl
from drivectl.tracefile.format import Trace


def run(effect: str, controller: str, out: Path, duration: float) -> dict[str, object]:
    common = ["trace", "--axis", "x", "--controller", controller, "--sim", "--no-plot", "--quiet",
              "--effect", effect, "--duration", str(duration)]
    if drivectl([*common, "--out", str(out / "before")]) != 0:
        raise SystemExit("trace (before) failed")
    before = Trace.read(out / "before" / "x.csv")
    if drivectl(["explain", str(out / "before" / "x.csv"), "--plant", "rigid-x", "--quiet", "--json",
                 "--out", str(out / "before")]) != 0:
        raise SystemExit("explain failed")
    model = out / "before" / "x.explain.plant.toml"
    if drivectl([*common, "--model", str(model), "--out", str(out / "after")]) != 0:
        raise SystemExit("trace (after) failed")
    after = Trace.read(out / "after" / "x.csv")

    def err(tr: Trace) -> dict[str, float]:
        e = (tr.ref - tr.pos) * 1e6
        return {"max_um": float(np.max(np.abs(e))), "rms_um": float(np.sqrt(np.mean(e * e)))}

    return {"effect": effect, "controller": controller, "before": err(before), "after": err(after),
            "model": str(model)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--effect", default="stribeck:excess_force=15,velocity=0.002")
    ap.add_argument("--controller", default="mbc")
    ap.add_argument("--duration", type=float, default=5.5)
    ap.add_argument("--out", help="folder for the traces (default: a temporary one)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        res = run(args.effect, args.controller, out, args.duration)
    if args.json:
        print(json.dumps(res))
    else:
        b, a = res["before"], res["after"]
        print(f"machine: rigid-x + {res['effect']}; controller {res['controller']}")
        print(f"tracking error with the nominal model:   max {b['max_um']:.1f} um, RMS {b['rms_um']:.2f} um")
        print(f"tracking error with the explained model: max {a['max_um']:.1f} um, RMS {a['rms_um']:.2f} um")
    return 0


if __name__ == "__main__":
    sys.exit(main())
