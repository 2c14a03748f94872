"""The resident loop on the wall clock with the web console attached: does it keep its deadlines?

Rows, each on the embedded machine's axis x (emulated CiA 402 drive on the in-process virtual bus, the
loop in its own thread at 1 kHz on the wall clock), the axis enabled and holding for --seconds:

* no-client: the console served (``drivectl ui``'s server in this process), nobody connected;
* ws-client: one websocket client as the page is one: the status every 100 ms and the live scope of four
  channels (1 kHz, read from the ring), decoded as JSON;
* browser: Debian's chromium headless with the page open on the Scope tab, drawing live (skipped, with
  the reason, where chromium + chromedriver are missing).

Columns: cycles, missed deadlines (fraction), worst lateness (ms, since the session's start), drive stops,
and the lateness percentiles of the counted part (ms, from the loop's histogram, ``status()["latency_ms"]``).
The figures are wall-clock measurements: quote the machine's load with them (printed).

    python bench/ui_loop.py [--seconds 30] [--rounds 1] [--loop process|thread] [--json]

``--rounds N``: the three rows N times, interleaved (no client, websocket, browser, no client, ...), so a
drift of the host's load falls on every row alike; each row's figures pool its N runs (its cycles and
missed slots summed), and the table adds the spread of the row's runs.

``--loop``: where the loop runs (default process: the console, its server and the browser's requests in
this process, the loop in its own; ``thread``: the loop a thread of this process).

--json prints exactly {"no_client_missed_fraction", "ws_client_missed_fraction", "browser_missed_fraction",
"no_client_worst_late_ms", "ws_client_worst_late_ms", "browser_worst_late_ms"} (null for a row that could
not run). Target: the same missed-deadline fraction with a browser attached as without (within the noise
of the machine), below 0.5 % on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import threading
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))


def _row(seconds: float, client: str, tmp: Path, loop: str = "process") -> dict | None:
    import drivectl
    from drivectl.tools.ui.command import bind, start_in_thread, url_of
    from drivectl.tools.ui.console import Console
    from drivectl.tools.ui.server import WebConsole

    driver = None
    if client == "browser":
        chrome, chromedriver = shutil.which("chromium"), shutil.which("chromedriver")
        if not chrome or not chromedriver:
            print("browser row skipped: no chromium + chromedriver here", file=sys.stderr)
            return None
    with drivectl.connect(axes=["x"], clock="wall", fault_dir=None, loop=loop) as m:
        console = Console(m, tmp).start()
        web = WebConsole(console)
        sock = bind("127.0.0.1", 0)
        server, thread = start_in_thread(web, sock)
        url = url_of(sock, web.token, True)
        stop = threading.Event()
        reader = None
        try:
            m.axes["x"].enable()
            if client == "ws":
                reader = threading.Thread(target=_ws_client, args=(url, stop), daemon=True)
                reader.start()
            elif client == "browser":
                from ui_helpers import make_driver

                driver = make_driver(shutil.which("chromium"), shutil.which("chromedriver"), tmp / "profile")
                driver.get(url)
                driver.find_element("css selector", '[data-testid="tab-scope"]').click()
            threading.Event().wait(2.0)  # connected and streaming before the counted part
            st0, lat0 = m.status(), _latency_copy(m.loop.latency)
            threading.Event().wait(seconds)
            st, lat = m.status(), _latency_copy(m.loop.latency)
        finally:
            stop.set()
            if driver is not None:
                driver.quit()
            if reader is not None:
                reader.join(5)
            server.should_exit = True
            thread.join(10)
            sock.close()
            console.conductor.stop()
    cycles = st["cycles"] - st0["cycles"]
    missed = st["missed_deadlines"] - st0["missed_deadlines"]
    row = {"cycles": cycles, "missed": missed, "missed_fraction": missed / max(cycles + missed, 1),
           "worst_late_ms": st["worst_late_ms"],
           "drive_stops": st["faults"] - st0["faults"]}
    lat.n -= lat0.n  # the counted part's lateness only (its maximum stays the session's: a histogram has no other)
    lat.counts = [a - b for a, b in zip(lat.counts, lat0.counts, strict=True)]
    row["latency_ms"] = lat.percentiles_ms()
    return row


def _latency_copy(rec):
    from drivectl.controllers.runtime.timing import LatencyRecord

    out = LatencyRecord()
    out.counts, out.n, out.max = list(rec.counts), rec.n, rec.max
    return out


def _ws_client(url: str, stop: threading.Event) -> None:
    from websockets.sync.client import connect

    base, token = url.split("/?token=")
    with connect(base.replace("http", "ws") + f"/ws?token={token}") as ws:
        ws.send(json.dumps({"id": 1, "op": "scope", "axis": "x", "window_s": 5,
                            "channels": ["reference", "position", "following_error", "effort"]}))
        while not stop.is_set():
            try:
                json.loads(ws.recv(timeout=0.5))
            except TimeoutError:
                continue


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="counted seconds per row (default 30)")
    ap.add_argument("--rounds", type=int, default=1,
                    help="the rows this many times, interleaved; each row pools its runs (default 1)")
    ap.add_argument("--loop", choices=("process", "thread"), default="process",
                    help="the loop in its own process (default) or a thread of this one")
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds: at least 1, got {args.rounds}")
    runs: dict[str, list[dict | None]] = {"no_client": [], "ws_client": [], "browser": []}
    clients = {"no_client": "none", "ws_client": "ws", "browser": "browser"}
    with tempfile.TemporaryDirectory() as d:
        for n in range(args.rounds):
            for name, client in clients.items():
                if n and runs[name][0] is None:
                    continue  # could not run (said why the first time)
                if args.rounds > 1:
                    print(f"round {n + 1}/{args.rounds}: {name}", file=sys.stderr)
                runs[name].append(_row(args.seconds, client, Path(d), args.loop))
    rows = {name: _pool(r) for name, r in runs.items()}
    load = os.getloadavg()
    if args.json:
        out = {}
        for name in rows:
            r = rows[name]
            out[f"{name}_missed_fraction"] = None if r is None else r["missed_fraction"]
        for name in rows:
            r = rows[name]
            out[f"{name}_worst_late_ms"] = None if r is None else r["worst_late_ms"]
        print(json.dumps(out))
        return
    print(f"loop ({args.loop}) at 1 kHz on the wall clock, x holding, {args.seconds:g} s per row; load average "
          f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f} (other jobs disturb these figures)")
    print(f"{'row':<10} {'cycles':>8} {'missed %':>9} {'worst ms':>9} {'stops':>6}  lateness percentiles (ms)")
    for name, r in rows.items():
        if r is None:
            print(f"{name:<10} {'-':>8}")
            continue
        pct = ", ".join(f"{k} {v:.3g}" for k, v in r["latency_ms"].items() if k != "max")
        print(f"{name:<10} {r['cycles']:>8} {r['missed_fraction'] * 100:>9.3f} {r['worst_late_ms']:>9.2f} "
              f"{r['drive_stops']:>6}  {pct or '-'}")
    if args.rounds > 1:
        for name, r in rows.items():
            if r is not None:
                print(f"{name:<10} per run, missed %: " + ", ".join(f"{f * 100:.3f}" for f in r["per_run"]))
        base = rows["no_client"]
        for name in ("ws_client", "browser"):
            if rows[name] is not None and base is not None:
                print(f"{name} - no_client: {(rows[name]['missed_fraction'] - base['missed_fraction']) * 100:+.3f} "
                      "percentage point (pooled)")


def _pool(runs: list[dict | None]) -> dict | None:
    """One row's runs as one: cycles, missed slots and stops summed, the worst lateness the worst of them,
    the percentiles those of the last run (a histogram per run), and each run's missed fraction."""
    done = [r for r in runs if r is not None]
    if not done:
        return None
    cycles = sum(r["cycles"] for r in done)
    missed = sum(r["missed"] for r in done)
    return {"cycles": cycles, "missed": missed, "missed_fraction": missed / max(cycles + missed, 1),
            "worst_late_ms": max(r["worst_late_ms"] for r in done),
            "drive_stops": sum(r["drive_stops"] for r in done), "latency_ms": done[-1]["latency_ms"],
            "per_run": [r["missed_fraction"] for r in done]}


if __name__ == "__main__":
    main()
