"""The console's Health page in a real browser (Debian's chromium, headless): the fleet table from the
store, an axis's alarms and trend panels. The store's fits are written here (a step in the viscous
scale at run 4), so that the page, not the method, is what is tested (tests/test_health_report.py
tests the method on emulated histories)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from ui_helpers import browser_or_skip, make_driver, ui_stack_or_skip

ui_stack_or_skip()
pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")
CHROME, CHROMEDRIVER = browser_or_skip()

from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

WAIT_S = 60


def _store(root):
    from drivectl.tools.health.store import Store
    from drivectl.tracefile.format import Trace

    rng = np.random.default_rng(5)
    t0 = datetime(2026, 11, 2, 6, tzinfo=UTC)
    with Store(root / "store") as s:
        for run in range(10):
            t = np.arange(200) * 1e-3
            ref = 0.01 * np.sin(2 * np.pi * t)
            path = Trace({"time_s": t, "ref_m": ref, "pos_m": ref + 1e-7 * rng.standard_normal(200),
                          "effort": 10 * rng.standard_normal(200)},
                         {"axis": "x", "dt_s": "0.001", "plant": "rigid-x", "stop": "done",
                          "started_utc": (t0 + run * timedelta(hours=8)).strftime("%Y-%m-%dT%H:%M:%SZ")}
                         ).write(root / f"x-{run}.csv")
            sha = s.ingest(path, "press-7").sha256
            scale = 1.0 + 0.01 * rng.standard_normal() + (0.3 if run >= 4 else 0.0)
            gap_model = 2e-6 if run < 4 else 3e-5
            s.add_fits(sha, [("viscous", "scale", scale, None, 2e-6),
                             ("coulomb", "force_pos", 45.0 + rng.standard_normal() * 0.2, None, gap_model),
                             ("coulomb", "force_neg", 47.0 + rng.standard_normal() * 0.2, None, gap_model),
                             ("mass", "mass", 88.0 + rng.standard_normal() * 0.3, None, gap_model)])
    return root / "store"


def test_the_health_page_shows_the_fleet_and_an_axis_alarm_with_its_panels(tmp_path):
    import drivectl
    from drivectl.tools.ui.command import bind, start_in_thread, url_of
    from drivectl.tools.ui.console import Console
    from drivectl.tools.ui.server import WebConsole

    store = _store(tmp_path)
    m = drivectl.connect(axes=["x"], fault_dir=tmp_path)
    console = Console(m, tmp_path / "traces", health_store=store)
    sock = bind("127.0.0.1", 0)
    server = thread = None
    driver = make_driver(CHROME, CHROMEDRIVER, tmp_path / "chromium-profile")
    try:
        console.start()
        web = WebConsole(console)
        server, thread = start_in_thread(web, sock)
        driver.get(url_of(sock, web.token, True))
        wait = WebDriverWait(driver, WAIT_S, poll_frequency=0.05)
        driver.find_element(By.CSS_SELECTOR, '[data-testid="tab-health"]').click()
        row = wait.until(lambda d: d.find_element(By.CSS_SELECTOR, '[data-testid="health-row-press-7-x"]'))
        assert "viscous.scale from run 4" in row.text
        row.click()
        wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, '[data-testid="health-alarm-viscous-scale"]'))
        assert "10 runs, 1 alarm" in driver.find_element(By.CSS_SELECTOR, '[data-testid="health-title"]').text
        shown = wait.until(lambda d: d.execute_script(
            "const p = document.querySelector('[data-testid=health-panel-viscous]');"
            "return p && p.data ? {n: p.data.length, y: p.data[1].y.length, shapes: p.layout.shapes.length,"
            " title: p.layout.title.text} : null;"))
        assert shown["y"] == 10 and shown["title"] == "viscous  ALARM"
        assert shown["shapes"] == 2  # the limit (1.5) and the onset
        assert {"coulomb", "mass"} <= set(driver.execute_script(
            "return [...document.querySelectorAll('[data-testid^=health-panel-]')]"
            ".map(e => e.dataset.testid.slice(13));"))
        assert driver.find_element(By.CSS_SELECTOR, '[data-testid="health-machine"]').get_attribute("value") == \
            "emulated"
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE" and "favicon" not in e["message"]]
        assert errors == []
    finally:
        driver.quit()
        if server is not None:
            server.should_exit = True
            thread.join(10)
        sock.close()
        states = console.close()
    assert all(s not in ("Operation Enabled", "Quick Stop Active") for s in states.values()), states
