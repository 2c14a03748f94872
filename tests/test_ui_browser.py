"""Issue 28 point 4: the web console in a real browser (Debian's chromium, headless, driven by selenium).

The machine runs on the lockstep clock paced to the wall clock (tools/ui/console.py Conductor): what is
asserted about the axes is read from the session (drive-reported power state, the loop's cycles and
ring), never from wall-clock timing; the browser only gets generous waits. Screenshots of every page
go to the test's output folder (and to $DRIVECTL_UI_SHOTS when set: docs/img/ui-scope.png comes from
there)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from ui_helpers import browser_or_skip, get, get_json, make_driver, running_console, stop_distance, ui_stack_or_skip

ui_stack_or_skip()
CHROME, CHROMEDRIVER = browser_or_skip()

from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

WAIT_S = 60  # generous: the browser and a loaded machine (2 cores, several jobs)


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    driver = make_driver(CHROME, CHROMEDRIVER, tmp_path_factory.mktemp("chromium-profile"))
    try:
        yield driver
    finally:
        driver.quit()


def tid(driver, name):
    return driver.find_element(By.CSS_SELECTOR, f'[data-testid="{name}"]')


def text(driver, name):
    """An element's shown text, read in one script (the page rebuilds some, e.g. the loop table, on every
    status: a found element may go stale before its text is read)."""
    return driver.execute_script(f"const e = document.querySelector('[data-testid=\"{name}\"]');"
                                 "if (!e) throw new Error('no element ' + arguments[0]); return e.innerText.trim();",
                                 name)


def wait_for(driver, cond, what, timeout=WAIT_S):
    try:
        return WebDriverWait(driver, timeout, poll_frequency=0.05).until(lambda d: cond(), message=what)
    except Exception:
        try:  # what the page said last: the reason, most of the time
            what += f" (page message: {text(driver, 'message')!r})"
            what += f" (page log: {driver.execute_script('return window.__drivectl.log')})"
            what += f" (browser log: {driver.get_log('browser')[-5:]})"
        except Exception:  # noqa: BLE001 - no page to ask
            pass
        if os.environ.get("DRIVECTL_UI_DEBUG"):
            import faulthandler

            faulthandler.dump_traceback(all_threads=True)
        raise AssertionError(f"timed out waiting for: {what}") from None


def shot(driver, out: Path, name: str) -> Path:
    path = out / "screenshots" / f"{name}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    driver.save_screenshot(str(path))
    extra = os.environ.get("DRIVECTL_UI_SHOTS")
    if extra:
        Path(extra).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(extra) / path.name)
    return path


def chart_series(driver, name, chart="scope"):
    """What a chart shows of a channel: points, first and last time, first, last, min and max value."""
    return driver.execute_script(
        f"const d = document.querySelector('[data-testid={chart}]').data || [];"
        f"const s = d.find(s => s.name.startsWith('{name} ')); if (!s || !s.x.length) return null;"
        "return {n: s.x.length, t0: s.x[0], t1: s.x[s.x.length - 1], y0: s.y[0], y1: s.y[s.y.length - 1],"
        " min: Math.min(...s.y), max: Math.max(...s.y), name: s.name,"
        " x: s.x.length <= 2000 ? s.x : null, y: s.y.length <= 2000 ? s.y : null};")


def arm(driver, trigger, pre, post, **level):
    """The scope's trigger fields filled in and Arm pressed."""
    Select(tid(driver, "scope-trigger")).select_by_value(trigger)
    if level:
        Select(tid(driver, "scope-level-channel")).select_by_visible_text(level["channel"])
        Select(tid(driver, "scope-direction")).select_by_visible_text(level["direction"])
        tid(driver, "scope-level").clear()
        tid(driver, "scope-level").send_keys(level["level"])
    for name, value in (("scope-pre", pre), ("scope-post", post)):
        tid(driver, name).clear()
        tid(driver, name).send_keys(value)
    tid(driver, "scope-arm").click()


def choose(driver, testid, value):
    """Select ``value`` in a select the page may be filling again (the trace list loads on each tab
    click): set in one script, once the option is there, so no option element goes stale."""
    wait_for(driver, lambda: driver.execute_script(
        f"const s = document.querySelector('[data-testid={testid}]');"
        "if (![...s.options].some(o => o.value === arguments[0])) return false;"
        "s.value = arguments[0]; return s.value === arguments[0];", value), f"{value!r} chosen in {testid}")


def open_page(driver, url):
    driver.get(url)
    wait_for(driver, lambda: driver.execute_script("return !!(window.__drivectl && window.__drivectl.built)"),
             "the page got the machine's first status")


def enable(driver, axis):
    tid(driver, "tab-axis").click()
    tid(driver, f"enable-{axis}").click()
    wait_for(driver, lambda: text(driver, f"axis-power-{axis}") == "servo, Operation Enabled", f"{axis} enabled")


def test_the_page_needs_the_token_and_loads_with_it(tmp_path, browser):
    with running_console(tmp_path / "traces") as (console, web, url):
        base = url.split("/?")[0]
        assert get(base + "/")[0] == 403
        assert get(base + "/?token=wrong")[0] == 403
        assert get(base + "/api/status")[0] == 403
        assert get(base + "/static/app.js")[0] == 403
        code, body = get(url)
        assert code == 200 and b"drivectl" in body
        from websockets.exceptions import InvalidStatus
        from websockets.sync.client import connect as ws_connect

        with pytest.raises(InvalidStatus):
            ws_connect(base.replace("http", "ws") + "/ws").close()
        browser.delete_all_cookies()
        browser.get(base + "/")
        assert "token is required" in browser.find_element(By.TAG_NAME, "body").text
        open_page(browser, url)
        assert tid(browser, "stop-all").is_displayed()
        wait_for(browser, lambda: text(browser, "power-x") == "Switch On Disabled", "x's power shown")
        assert text(browser, "position-x") == f"{console.m.axes['x'].position * 1e3:.4f}"
        # the loop's timing health: its counters and lateness percentiles, as status() has them
        wait_for(browser, lambda: int(text(browser, "loop-cycles")) > 0, "the loop's cycles shown")
        assert text(browser, "loop-missed_deadlines") == "0"  # lockstep: nothing is late
        assert text(browser, "loop-latency_ms").startswith("p50=")
        shot(browser, tmp_path, "ui-machine")


def test_holding_jog_moves_x_and_release_or_a_lost_connection_stops_it_within_the_dead_man(tmp_path, browser):
    with running_console(tmp_path / "traces") as (console, web, url):
        open_page(browser, url)
        enable(browser, "x")
        x = console.m.axes["x"]
        start = x.position
        button = tid(browser, "jog-plus-x")
        ActionChains(browser).click_and_hold(button).perform()
        wait_for(browser, lambda: x.position > start + 0.5e-3, "x moved 0.5 mm while the jog button was held")
        assert "x" in console.jogs and console.jogs["x"].last_renewal_cycle > 0
        shot(browser, tmp_path, "ui-axis")
        ActionChains(browser).release(button).perform()
        token = web.token
        base = url.split("/?")[0]
        wait_for(browser, lambda: len(get_json(base, "/api/jogs", token)) == 1, "the jog's end logged")
        ev = get_json(base, "/api/jogs", token)[0]
        assert ev["axis"] == "x" and ev["why"] == "release"
        # from the ring: the reference came to rest within the dead-man interval of the last renewal
        assert ev["standstill_after_renewal_s"] is not None
        assert 0 <= ev["standstill_after_renewal_s"] <= ev["deadman_s"]
        # from the release's arrival (its loop cycle) to standstill: the stop's own distance + 2 cycles, no more
        v, dt = ev["velocity_m_s"], console.m.loop.dt
        bound = stop_distance(v, console.m.loop.axes["x"].motion) + 2 * abs(v) * dt
        assert ev["travel_after_stop_m"] is not None and 0 <= ev["travel_after_stop_m"] <= bound, (ev, bound)
        print(f"browser: release to standstill {ev['travel_after_stop_m'] * 1e6:.1f} um in "
              f"{ev['standstill_after_stop_s'] * 1e3:.0f} ms at {v * 1e3:g} mm/s (bound {bound * 1e6:.1f} um)")
        held_at = x.position
        # the axis holds where it stopped: still enabled, no command under way
        wait_for(browser, lambda: console.m.status()["axes"]["x"]["move"] is None, "no command under way")
        assert x.power.value == "Operation Enabled" and abs(x.position - held_at) < 2e-6  # mbc holds

        # a lost connection: the page's websocket goes away while the button is held
        ActionChains(browser).click_and_hold(button).perform()
        moved_from = x.position
        wait_for(browser, lambda: x.position > moved_from + 0.3e-3, "x moving again")
        browser.execute_script("const w = window.__drivectl.ws; w.onclose = null; w.close();")
        wait_for(browser, lambda: len(get_json(base, "/api/jogs", token)) == 2, "the second jog's end logged")
        ev = get_json(base, "/api/jogs", token)[1]
        assert ev["why"] in ("connection lost", "dead man (renewals stopped)")
        assert 0 <= ev["standstill_after_renewal_s"] <= ev["deadman_s"]
        ActionChains(browser).release(button).perform()

        # a hidden tab: the page stops the jog itself
        open_page(browser, url)
        tid(browser, "tab-axis").click()
        button = tid(browser, "jog-minus-x")
        ActionChains(browser).click_and_hold(button).perform()
        wait_for(browser, lambda: "x" in console.jogs, "jog held")
        browser.execute_script("Object.defineProperty(document, 'hidden', {value: true, configurable: true});"
                               "document.dispatchEvent(new Event('visibilitychange'));")
        wait_for(browser, lambda: len(get_json(base, "/api/jogs", token)) == 3, "the third jog's end logged")
        ev = get_json(base, "/api/jogs", token)[2]
        assert ev["why"] == "hidden tab" and 0 <= ev["standstill_after_renewal_s"] <= ev["deadman_s"]
        ActionChains(browser).release(button).perform()


def test_the_scope_shows_live_data_freezes_with_cursors_and_saves_a_trace(tmp_path, browser):
    from drivectl.tracefile.format import Trace

    out = tmp_path / "traces"
    with running_console(out) as (console, web, url):
        open_page(browser, url)
        enable(browser, "x")
        field = tid(browser, "move-to-input-x")
        field.clear()
        field.send_keys("3mm")
        tid(browser, "move-to-x").click()
        x = console.m.axes["x"]
        wait_for(browser, lambda: abs(x.position - 3e-3) < 5e-6 and console.m.status()["axes"]["x"]["move"] is None,
                 "x at 3 mm")
        tid(browser, "tab-scope").click()
        series = lambda name: chart_series(browser, name)  # noqa: E731

        wait_for(browser, lambda: (series("position") or {}).get("n", 0) > 50, "data plotted")
        t1 = series("position")["t1"]
        wait_for(browser, lambda: series("position")["t1"] > t1 + 0.2, "the scope's time axis grows (live)")
        s = series("position")
        assert abs(s["y1"] - x.position * 1e3) < 0.01  # mm: the axis's own value
        assert s["max"] == pytest.approx(3.0, abs=1e-3)  # mm: no overshoot beyond 1 um
        samples = browser.execute_script("return window.__drivectl.scope.samples")
        assert samples > 500  # 1 kHz samples arrived; the plot shows them decimated per pixel column
        shot(browser, tmp_path, "ui-scope")

        # a move-start trigger with pre/post: the move appears around t = 0, frozen
        Select(tid(browser, "scope-trigger")).select_by_value("move")
        for name, value in (("scope-pre", "50ms"), ("scope-post", "400ms")):
            tid(browser, name).clear()
            tid(browser, name).send_keys(value)
        tid(browser, "scope-arm").click()
        wait_for(browser, lambda: console.capture is not None, f"capture armed ({text(browser, 'message')})")
        tid(browser, "tab-axis").click()
        field = tid(browser, "move-to-input-x")
        field.clear()
        field.send_keys("1mm")
        tid(browser, "move-to-x").click()
        tid(browser, "tab-scope").click()
        wait_for(browser, lambda: "frozen" in text(browser, "scope-state"), "the triggered capture shown")
        s = series("position")
        assert s["t0"] == pytest.approx(-0.05, abs=2e-3) and s["t1"] == pytest.approx(0.4, abs=2e-3)
        assert s["y0"] == pytest.approx(3.0, abs=0.01) and s["y1"] < 2.0  # the move in the window
        browser.execute_script("window.__drivectl.setCursor(-0.01); window.__drivectl.setCursor(0.3);")
        rows = tid(browser, "scope-readout").find_elements(By.TAG_NAME, "tr")
        assert len(rows) >= 3 and "B − A" in rows[0].text
        shot(browser, tmp_path, "ui-scope-capture")
        tid(browser, "scope-save").click()
        wait_for(browser, lambda: "wrote" in text(browser, "message"), "saved")
        csv = sorted(out.glob("x-scope-*.csv"))
        assert len(csv) == 1 and csv[0].with_suffix(".png").is_file()
        tr = Trace.read(csv[0])
        assert len(tr) == 451 and tr.meta["capture_trigger"] == "move"

        # Traces: the saved capture listed, plotted, summarised
        tid(browser, "tab-traces").click()
        wait_for(browser, lambda: browser.find_elements(By.CSS_SELECTOR, f'[data-testid="trace-row-{csv[0].name}"]'),
                 "the saved trace listed")
        browser.execute_script(f"document.querySelector('[data-testid=\"trace-row-{csv[0].name}\"]').click()")
        wait_for(browser, lambda: "max_um" in text(browser, "trace-summary"), "its summary")
        n = browser.execute_script("return document.querySelector('[data-testid=trace-plot]').data.length")
        assert n >= 3
        assert "effort [N]" in [chart_series(browser, c, "trace-plot")["name"] for c in ("position", "effort")]
        # zoom (as a drag on the chart reports it): the range shown is drawn again, every sample of it
        browser.execute_script("Plotly.relayout(document.querySelector('[data-testid=trace-plot]'),"
                               " {'xaxis.range[0]': 0.0, 'xaxis.range[1]': 0.05})")
        wait_for(browser, lambda: chart_series(browser, "position", "trace-plot")["t1"] < 0.06, "zoomed in")
        z = chart_series(browser, "position", "trace-plot")
        rows = [t for t in tr.time if 0.0 <= t <= 0.05]
        assert len(rows) <= z["n"] <= len(rows) + 4  # full resolution (a sample either side of the range)
        shot(browser, tmp_path, "ui-traces")

        # Explain refuses a capture too short to decide: one visible line, as the command says it
        tid(browser, "tab-explain").click()
        choose(browser, "explain-trace", csv[0].name)
        tid(browser, "explain-run").click()
        wait_for(browser, lambda: text(browser, "explain-state") in ("failed",) or
                 text(browser, "explain-state").startswith("done"), "explain finished", timeout=300)
        assert text(browser, "explain-state") == "failed" and "cannot decide" in text(browser, "message")


def test_the_scope_triggers_on_a_level_and_freezes_what_it_shows(tmp_path, browser):
    out = tmp_path / "traces"
    with running_console(out) as (console, web, url):
        open_page(browser, url)
        enable(browser, "x")
        x = console.m.axes["x"]
        tid(browser, "tab-scope").click()
        full = lambda: (lambda s: s is not None and s["t1"] - s["t0"] > 4.95)(chart_series(browser, "position"))  # noqa: E731
        wait_for(browser, full, "the scope's 5 s window filled")

        # Freeze: the window just shown, as a capture (trigger now, pre = the window, at most the ring)
        tid(browser, "scope-freeze").click()
        wait_for(browser, lambda: "frozen" in text(browser, "scope-state"), "frozen")
        assert "trigger now" in text(browser, "scope-state")
        s = chart_series(browser, "position")
        assert s["t0"] == pytest.approx(-4.9, abs=2e-3) and s["t1"] == pytest.approx(0.0, abs=2e-3)
        assert s["max"] == pytest.approx(x.position * 1e3, abs=1e-3)

        # a level trigger: position rising through 2 mm, typed with its unit
        arm(browser, "level", "20ms", "100ms", channel="position", direction="rising", level="2mm")
        wait_for(browser, lambda: "trigger position rising through 2 mm" in text(browser, "message"),
                 "level capture armed")  # the freeze's "armed" line is there before: wait for this one's
        tid(browser, "tab-axis").click()
        tid(browser, "move-to-input-x").clear()
        tid(browser, "move-to-input-x").send_keys("3mm")
        tid(browser, "move-to-x").click()
        tid(browser, "tab-scope").click()
        wait_for(browser, lambda: "trigger position rising through 2 mm" in text(browser, "scope-state"),
                 "the level capture shown")
        s = chart_series(browser, "position")
        assert s["t0"] == pytest.approx(-0.02, abs=2e-3) and s["t1"] == pytest.approx(0.1, abs=2e-3)
        at0 = s["y"][min(range(len(s["x"])), key=lambda i: abs(s["x"][i]))]
        before = [y for t, y in zip(s["x"], s["y"], strict=True) if t < -1e-9]
        assert at0 >= 2.0 and max(before) < 2.0  # crossed 2 mm rising at t = 0
        shot(browser, tmp_path, "ui-scope-level")

        # a bad level: one line, nothing armed
        seq = console.capture_seq
        arm(browser, "level", "20ms", "100ms", channel="position", direction="rising", level="2 furlongs")
        wait_for(browser, lambda: "furlongs" in text(browser, "message"), "the bad level refused")
        assert "error" in tid(browser, "message").get_attribute("class") and console.capture_seq == seq



def test_explain_on_a_recorded_run_shows_its_report_and_plot(tmp_path, browser):
    from drivectl.profiles.library import load_profile

    out = tmp_path / "traces"
    with running_console(out, axes=("x",)) as (console, web, url):
        m = console.m

        def record() -> None:  # a run of x's profile through the session, on the console's own thread
            x = m.axes["x"]
            x.enable()
            h = x.run(load_profile(m.config.axis("x").profile), approach=True)
            h.wait(120)
            h.trace.write(out / "x-run.csv")

        console.conductor.call(record).result(600)
        open_page(browser, url)
        tid(browser, "tab-explain").click()
        wait_for(browser, lambda: "x-run.csv" in text(browser, "explain-trace"), "the run listed")
        choose(browser, "explain-trace", "x-run.csv")
        tid(browser, "explain-run").click()
        wait_for(browser, lambda: text(browser, "explain-state") in ("failed",) or
                 text(browser, "explain-state").startswith("done"), "explain finished", timeout=600)
        assert text(browser, "explain-state").startswith("done"), text(browser, "message")
        assert "gap" in text(browser, "explain-report")
        wait_for(browser, lambda: browser.execute_script(
            "const i = document.querySelector('[data-testid=explain-png]'); return i.complete && i.naturalWidth > 0"),
            "explain's plot shown")
        shot(browser, tmp_path, "ui-explain")


def test_an_injected_fault_appears_decoded_triggers_the_scope_and_its_reset_works(tmp_path, browser):
    from drivectl.tracefile.format import Trace

    out = tmp_path / "traces"
    with running_console(out, faults=["x/emcy-fault:code=0x2310@0.3"]) as (console, web, url):
        open_page(browser, url)
        # the scope armed on a fault first: the drive faults 0.3 s after the enable; the stop is in the post samples
        tid(browser, "tab-scope").click()
        arm(browser, "fault", "100ms", "200ms")
        wait_for(browser, lambda: "armed" in text(browser, "message"), "fault capture armed")
        enable(browser, "x")
        tid(browser, "tab-scope").click()
        wait_for(browser, lambda: "trigger fault" in text(browser, "scope-state"), "the fault capture shown")
        s = chart_series(browser, "position")
        assert s["t0"] == pytest.approx(-0.1, abs=2e-3) and s["t1"] == pytest.approx(0.2, abs=2e-3)
        tid(browser, "scope-save").click()
        wait_for(browser, lambda: "wrote" in text(browser, "message"), "saved")
        tr = Trace.read(sorted(out.glob("x-scope-*.csv"))[-1])
        assert tr.meta["capture_trigger"] == "fault" and "0x2310" in tr.meta["capture_detail"]
        # -0.1 .. 0.2 s at 1 kHz, the cycle that detected the fault maybe without a sample (capture.py)
        assert tr.time[0] == pytest.approx(-0.1) and tr.time[-1] == pytest.approx(0.2) and len(tr) in (300, 301)
        shot(browser, tmp_path, "ui-scope-fault")
        tid(browser, "tab-machine").click()
        wait_for(browser, lambda: "0x2310" in text(browser, "fault-x"), "the drive's error shown decoded")
        assert text(browser, "power-x") == "Fault"
        assert console.m.axes["x"].power.value == "Fault"
        shot(browser, tmp_path, "ui-machine-fault")
        tid(browser, "fault-reset-x").click()
        wait_for(browser, lambda: text(browser, "power-x") == "Switch On Disabled", "the reset verified")
        wait_for(browser, lambda: text(browser, "fault-x") == "", "no fault shown")
        assert console.m.axes["x"].power.value == "Switch On Disabled"
        enable(browser, "x")  # and the axis can be enabled again


def test_stop_all_stops_every_axis_and_bad_input_moves_nothing(tmp_path, browser):
    with running_console(tmp_path / "traces") as (console, web, url):
        open_page(browser, url)
        enable(browser, "x")
        enable(browser, "y")
        m = console.m
        x, y = m.axes["x"], m.axes["y"]

        # bad input: one visible message each, nothing moves
        before = {n: a.position for n, a in m.axes.items()}
        for field, value, button, expect in (
                ("move-to-input-x", "20 furlongs", "move-to-x", "unit"),
                ("move-to-input-x", "9000mm", "move-to-x", "outside the soft limits"),
                ("move-by-input-x", "abc", "move-by-x", "not a number"),
                ("speed-x", "5000mm/s", "move-to-x", "max_velocity_m_s")):
            tid(browser, field).clear()
            tid(browser, field).send_keys(value)
            if field == "speed-x":
                tid(browser, "move-to-input-x").clear()
                tid(browser, "move-to-input-x").send_keys("2mm")
            tid(browser, button).click()
            wait_for(browser, lambda expect=expect: expect in text(browser, "message"), f"message for {value!r}")
            assert "error" in tid(browser, "message").get_attribute("class")
            assert len(text(browser, "message").splitlines()) == 1
            assert all(m.status()["axes"][n]["move"] is None for n in m.axes)
        tid(browser, "speed-x").clear()
        # a jog speed that is no speed: refused at the first request, the button's hold ends, nothing moves
        tid(browser, "jog-speed-x").clear()
        tid(browser, "jog-speed-x").send_keys("fast")
        button = tid(browser, "jog-plus-x")
        ActionChains(browser).click_and_hold(button).perform()
        wait_for(browser, lambda: "jog speed" in text(browser, "message"), "message for the jog speed")
        assert "error" in tid(browser, "message").get_attribute("class")
        assert browser.execute_script("return window.__drivectl.jog") is None and console.jogs == {}
        ActionChains(browser).release(button).perform()
        tid(browser, "jog-speed-x").clear()
        tid(browser, "jog-speed-x").send_keys("5mm/s")
        assert all(abs(a.position - before[n]) < 5e-6 for n, a in m.axes.items())
        shot(browser, tmp_path, "ui-bad-input")

        for axis in ("x", "y"):
            tid(browser, f"move-to-input-{axis}").clear()
            tid(browser, f"move-to-input-{axis}").send_keys("60mm")
            tid(browser, f"speed-{axis}").clear()
            tid(browser, f"speed-{axis}").send_keys("10mm/s")
            tid(browser, f"move-to-{axis}").click()
        wait_for(browser, lambda: x.position > 1e-3 and y.position > 1e-3, "both axes moving")
        browser.find_element(By.TAG_NAME, "body").send_keys(Keys.SPACE)  # the space bar: Stop all
        wait_for(browser, lambda: all(m.status()["axes"][n]["move"] is None for n in ("x", "y")), "both stopped")
        assert x.position < 30e-3 and y.position < 30e-3  # far short of the 60 mm target
        at = {n: m.axes[n].position for n in ("x", "y")}
        m_time = m.loop.cycle
        wait_for(browser, lambda: m.loop.cycle > m_time + 200, "0.2 s more")
        for n in ("x", "y"):  # holding where they stopped, enabled, as the drives report
            assert m.axes[n].power.value == "Operation Enabled" and abs(m.axes[n].position - at[n]) < 2e-6

        # the button does the same (a far target at 10 mm/s: the stop lands far short of it, however slow the page)
        tid(browser, "move-to-input-x").clear()
        tid(browser, "move-to-input-x").send_keys("-90mm")
        tid(browser, "move-to-x").click()
        wait_for(browser, lambda: m.status()["axes"]["x"]["move"] is not None, "x moving back")
        tid(browser, "stop-all").click()
        wait_for(browser, lambda: m.status()["axes"]["x"]["move"] is None, "x stopped by the button")
        assert x.position > -60e-3 and x.power.value == "Operation Enabled"
