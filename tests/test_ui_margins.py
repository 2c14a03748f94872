"""The console's Axis page after `drivectl bode --loop open --out <its folder>`: the figure and the margins."""

from __future__ import annotations

import json

import pytest
from ui_helpers import get, get_json, running_console, ui_stack_or_skip

from drivectl.machine.config import load_config
from drivectl.tools.commissioning.margins import JSON_KEYS, measure_open_loop, write_open_loop

ui_stack_or_skip()


@pytest.fixture(autouse=True)
def _embedded_config(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DRIVECTL_CONFIG", raising=False)


def test_axis_page_serves_the_last_open_loop_figure_and_its_margins(tmp_path) -> None:
    out = tmp_path / "traces"
    with running_console(out, axes=("x",)) as (_console, web, url):
        base = url.split("/?")[0]
        assert get_json(base, "/api/margins", web.token) == {}  # nothing measured yet: the card says how
        res = measure_open_loop(load_config(None), "x", sim=True, seconds=2, period_s=0.5)
        write_open_loop(res, out)
        got = get_json(base, "/api/margins", web.token)
        assert set(got) == {"x"} and got["x"]["png"] == "bode-open-x.png"
        m = got["x"]["margins"]
        assert {k: m[k] for k in JSON_KEYS} == json.loads(json.dumps(res.to_json())) and m["linear"] is True
        code, body = get(f"{base}/files/bode-open-x.png?token={web.token}")
        assert code == 200 and body[:8] == b"\x89PNG\r\n\x1a\n"
        assert get(f"{base}/api/margins")[0] == 403  # the token, as every request
    from drivectl.tools.ui import server

    app_js = (server.STATIC / "app.js").read_text()
    assert "loadMargins" in app_js and "/api/margins" in app_js and "margins-png-" in app_js


def test_the_axis_page_shows_the_figure_in_a_browser(tmp_path) -> None:
    """In Debian's chromium (headless): the Axis card of x shows the margins line and the PNG after a run."""
    from ui_helpers import browser_or_skip, make_driver

    chrome, chromedriver = browser_or_skip()
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    out = tmp_path / "traces"
    res = measure_open_loop(load_config(None), "x", sim=True, seconds=2, period_s=0.5)
    with running_console(out, axes=("x",)) as (_console, _web, url):
        write_open_loop(res, out)
        driver = make_driver(chrome, chromedriver, tmp_path / "profile")
        try:
            driver.get(url)
            wait = WebDriverWait(driver, 60, poll_frequency=0.05)
            wait.until(lambda d: d.execute_script("return !!(window.__drivectl && window.__drivectl.built)"))
            driver.find_element(By.CSS_SELECTOR, '[data-testid="tab-axis"]').click()
            wait.until(lambda d: d.execute_script(
                "const i = document.querySelector('[data-testid=margins-png-x]');"
                "return !!i && i.complete && i.naturalWidth > 0"), "the open-loop figure shown")
            line = driver.find_element(By.CSS_SELECTOR, '[data-testid="margins-line-x"]').text
            assert f"PM {res.margins.pm_deg.value:.1f}°" in line and "mbc" in line
        finally:
            driver.quit()
