"""Score `drivectl explain` on the generated test set (bench/explain_traces.py).

For every case: a trace through SimAxis with one hidden effect (or none), then ``explain`` against
the nominal plant. Per effect and overall: named right, false alarms (a clean trace named as an
effect), parameter error (share of named-right cases with every vocabulary parameter within 25 %),
median gap shrink (1 - gap_after / gap_before over the named-right cases) and seconds per trace.

    python bench/explain_score.py                 # full set, table
    python bench/explain_score.py --json          # exactly one JSON object on stdout
    python bench/explain_score.py --per-effect 2 --clean 4 --seed 7   # a smaller or another draw

Progress goes to stderr. Exit status 1 when a target of the issue is missed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from explain_traces import EFFECT_NAMES, cases, make_trace  # noqa: E402

from drivectl.plant_emulator.models import load_plant  # noqa: E402
from drivectl.tools.explain import PARAM_NAMES, explain  # noqa: E402

TARGETS = {"named_right": 0.90, "false_alarms": 0, "param_within_25pct": 0.90, "median_gap_shrink": 0.80,
           "seconds_per_trace": 5.0}


def param_ok(effect: str, fitted: dict[str, float], truth: dict[str, float], tol: float = 0.25) -> bool:
    return all(abs(fitted[k] / truth[k] - 1.0) <= tol for k in PARAM_NAMES[effect])


def worst_param_error(effect: str, fitted: dict[str, float], truth: dict[str, float]) -> float:
    return max(abs(fitted[k] / truth[k] - 1.0) for k in PARAM_NAMES[effect])


def score(per_effect: int, clean: int, seed: int, verbose: bool) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    todo = cases(per_effect, clean, seed)
    for i, case in enumerate(todo):
        try:
            trace, truth = make_trace(case)
        except RuntimeError as exc:
            print(f"[{i + 1}/{len(todo)}] skipped: {exc}", file=sys.stderr)
            continue
        t0 = time.perf_counter()
        res = explain(trace, load_plant(case.plant), source=case.label)
        sec = time.perf_counter() - t0
        right = res.effect == case.effect
        row = {"truth": case.effect, "named": res.effect, "right": right, "seconds": sec,
               "duration_s": float(trace.time[-1]), "label": case.label,
               "shrink": 1.0 - res.gap_after / res.gap_before if res.gap_before > 0 else 0.0,
               "gap_before": res.gap_before, "gap_after": res.gap_after}
        if right and case.effect != "none":
            row["param_ok"] = param_ok(case.effect, res.params, truth)
            row["param_err"] = worst_param_error(case.effect, res.params, truth)
        rows.append(row)
        if verbose:
            fitted = ", ".join(f"{k}={v:.4g}" for k, v in res.params.items())
            extra = f" err {row['param_err']:.1%}" if "param_err" in row else ""
            print(f"[{i + 1}/{len(todo)}] {'ok ' if right else 'BAD'} {case.label} -> {res.effect} ({fitted}){extra} "
                  f"gap {res.gap_before * 1e6:.2f}->{res.gap_after * 1e6:.2f} um {sec:.2f} s", file=sys.stderr)
    return summarise(rows)


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    def block(rs: list[dict[str, Any]]) -> dict[str, Any]:
        effect_rows = [r for r in rs if r["truth"] != "none"]
        right = [r for r in effect_rows if r["right"]]
        with_p = [r for r in right if "param_ok" in r]
        return {
            "n": len(rs),
            "named_right": sum(r["right"] for r in rs) / len(rs) if rs else float("nan"),
            "false_alarms": sum(1 for r in rs if r["truth"] == "none" and r["named"] != "none"),
            "param_within_25pct": sum(r["param_ok"] for r in with_p) / len(with_p) if with_p else float("nan"),
            "median_param_error": statistics.median(r["param_err"] for r in with_p) if with_p else float("nan"),
            "median_gap_shrink": statistics.median(r["shrink"] for r in right) if right else float("nan"),
            "seconds_per_trace": statistics.mean(r["seconds"] for r in rs) if rs else float("nan"),
            "confused_with": sorted({r["named"] for r in rs if not r["right"]}),
        }

    out = block(rows)
    out["seconds_per_10s_trace"] = (statistics.mean(r["seconds"] / r["duration_s"] * 10.0 for r in rows)
                                    if rows else float("nan"))
    out["per_effect"] = {e: block([r for r in rows if r["truth"] == e]) for e in ("none", *EFFECT_NAMES)}
    # effect traces only, for the overall shrink and parameter figures (none has neither)
    return out


def print_table(s: dict[str, Any]) -> None:
    head = (f"{'effect':<11} {'n':>3} {'named right':>11} {'false al.':>9} {'params<=25%':>11} {'med p.err':>9} "
            f"{'med shrink':>10} {'s/trace':>8}  confused with")
    print(head)
    print("-" * len(head))

    def pct(x: float) -> str:
        return "-" if x != x else f"{100 * x:.0f} %"

    for name, b in [*s["per_effect"].items(), ("overall", s)]:
        print(f"{name:<11} {b['n']:>3} {pct(b['named_right']):>11} {b['false_alarms']:>9} "
              f"{pct(b['param_within_25pct']):>11} {pct(b['median_param_error']):>9} "
              f"{pct(b['median_gap_shrink']):>10} {b['seconds_per_trace']:>8.2f}  {', '.join(b['confused_with'])}")
    print(f"\nseconds per 10 s of trace: {s['seconds_per_10s_trace']:.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-effect", type=int, default=8, help="traces per effect (default 8)")
    ap.add_argument("--clean", type=int, default=16, help="clean traces (default 16)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the draw (default 1)")
    ap.add_argument("--json", action="store_true", help="exactly one JSON object on stdout")
    ap.add_argument("--quiet", action="store_true", help="no per-trace progress on stderr")
    args = ap.parse_args(argv)
    s = score(args.per_effect, args.clean, args.seed, verbose=not args.quiet)
    ok = (s["named_right"] >= TARGETS["named_right"] and s["false_alarms"] <= TARGETS["false_alarms"]
          and s["param_within_25pct"] >= TARGETS["param_within_25pct"]
          and s["median_gap_shrink"] >= TARGETS["median_gap_shrink"]
          and s["seconds_per_10s_trace"] <= TARGETS["seconds_per_trace"])
    if args.json:
        print(json.dumps(s))
    else:
        print_table(s)
        print(f"targets: {'all met' if ok else 'MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
