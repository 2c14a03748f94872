"""The console's Health page without a browser: the fingerprint run through the console's command path
(refused on an axis that is not enabled; run, watched, its trace ingested), the fleet table and one
axis's panels from the store, and the analysis of new runs in a child process."""

from __future__ import annotations

import json
import time
import urllib.request
from pathlib import Path

import pytest
from ui_helpers import get_json, ui_stack_or_skip

ui_stack_or_skip()
pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")
pytest.importorskip("distributed")

SHORT = Path(__file__).with_name("data") / "health-short.toml"


def _post(url: str) -> dict:
    req = urllib.request.Request(url, data=b"{}", method="POST", headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=300) as r:
        return json.loads(r.read())


def test_the_health_page_runs_a_fingerprint_into_the_store_and_shows_its_trends(tmp_path):
    import drivectl
    from drivectl.machine.config import DEFAULT_CONFIG_TOML, load_config
    from drivectl.tools.ui.command import bind, start_in_thread, url_of
    from drivectl.tools.ui.console import USER_ERRORS, Console
    from drivectl.tools.ui.server import WebConsole

    # one run is the axis's baseline here (the default waits for three): the console's analysis, a child
    # process, reads this file
    path = tmp_path / "machine.toml"
    path.write_text(DEFAULT_CONFIG_TOML + f'\n[health]\nbaseline_runs = 1\n\n[axes.x.health]\nprofile = "{SHORT}"\n')
    cfg = load_config(path)
    out, store = tmp_path / "traces", tmp_path / "store"
    out.mkdir()
    m = drivectl.connect(cfg, axes=["x"], fault_dir=out)
    console = Console(m, out, health_store=store)
    sock = bind("127.0.0.1", 0)
    server = thread = None
    try:
        console.start()
        web = WebConsole(console)
        server, thread = start_in_thread(web, sock)
        base = url_of(sock, web.token, True).split("/?")[0]
        token = web.token
        assert get_json(base, "/api/health", token)["axes"] == []  # no store yet
        with pytest.raises(USER_ERRORS, match=r"^axis x: health run: not enabled") as exc:
            console.command("t", {"op": "health_run", "axis": "x"})
        assert "\n" not in str(exc.value) and not store.exists()
        console.command("t", {"op": "enable", "axis": "x"})
        line = console.command("t", {"op": "health_run", "axis": "x", "machine": "press-7"})
        assert line.startswith("x: fingerprint run started (machine press-7")
        with pytest.raises(USER_ERRORS, match="still running"):
            console.command("t", {"op": "health_run", "axis": "x"})
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # the status stream's watch, as the page's connection drives it
            st = get_json(base, "/api/status", token)["console"]["health"]
            if not st["running"] and st["last"] and st["last"]["state"] != "running":
                break
            time.sleep(0.2)
        last = st["last"]
        assert last["state"] == "done" and last["ingest"] == "added", last
        assert (out / last["trace"]).is_file()
        fleet = get_json(base, "/api/health", token)
        assert [(r["machine"], r["axis"], r["runs"], r["fitted"], r["worst"]) for r in fleet["axes"]] == \
            [("press-7", "x", 1, 0, None)]
        got = _post(f"{base}/api/health/analyze?token={token}")
        assert got["ok"] and "1 runs fitted, 0 failed" in got["line"], got
        axis = get_json(base, "/api/health/axis", token + "&machine=press-7&axis=x")
        assert axis["report"]["runs"] == 1 and axis["report"]["alarms"] == []
        assert {"viscous", "backlash", "coulomb"} <= set(axis["panels"])
        (scale,) = [s for s in axis["panels"]["viscous"] if s["param"] == "scale"]
        assert scale["runs"] == [0] and scale["limit"] == 1.5 and scale["alarm"] is False
        assert scale["values"][0] == pytest.approx(1.0, abs=0.05)
        code_page = urllib.request.urlopen(f"{base}/?token={token}", timeout=10).read().decode()
        assert 'data-testid="tab-health"' in code_page and "/static/health.js" in code_page
        assert urllib.request.urlopen(f"{base}/static/health.js?token={token}", timeout=10).status == 200
    finally:
        if server is not None:
            server.should_exit = True
            thread.join(10)
        sock.close()
        states = console.close()
    assert all(s not in ("Operation Enabled", "Quick Stop Active") for s in states.values()), states
