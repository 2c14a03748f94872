"""Issue 28 points 1, 3, 5 without a browser: ``drivectl ui`` as a process (URL with a token, loopback,
--listen's warning, Ctrl-C disables every axis), the console's validation, and the ring read."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest
from ui_helpers import get, machine_config, running_console, stop_distance, ui_stack_or_skip

ui_stack_or_skip()


UI = [sys.executable, "-m", "drivectl.tools.cli.main", "ui"]


def start_ui(tmp_path, *extra: str, env: dict[str, str] | None = None) -> tuple[subprocess.Popen, str]:
    env = {**(os.environ if env is None else env), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([*UI, "--port", "0", "--out",
                             str(tmp_path / "traces"), *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=tmp_path)
    url = ""
    for _ in range(10):  # the lines before the URL
        line = proc.stdout.readline()
        if line.startswith("open "):
            url = line.split()[1]
            break
    assert url, proc.stderr.read() if proc.poll() is not None else "no URL printed"
    return proc, url


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_drivectl_ui_serves_with_a_token_on_loopback_and_a_signal_disables_every_axis(tmp_path, sig):
    proc, url = start_ui(tmp_path, "--axis", "x")
    try:
        assert url.startswith("http://127.0.0.1:") and "token=" in url
        token = url.split("token=")[1]
        assert len(token) >= 24
        base = url.split("/?")[0]
        assert get(url)[0] == 200
        assert get(base + "/")[0] == 403
        assert get(f"{base}/static/plotly.min.js?token={token}")[0] == 200  # from plotly's wheel
        # enable x over the websocket, as the page does
        from websockets.sync.client import connect as ws_connect

        with ws_connect(base.replace("http", "ws") + f"/ws?token={token}") as ws:
            import json

            ws.send(json.dumps({"id": 1, "op": "enable", "axis": "x"}))
            while True:
                msg = json.loads(ws.recv(timeout=60))
                if msg["type"] == "reply":
                    break
            assert msg["ok"], msg
            assert "Operation Enabled" in msg["message"]
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == (0 if sig == signal.SIGINT else 143), err  # Ctrl-C is the way out; SIGTERM as the shell
    assert "closed: x Switch On Disabled" in err  # as the drive reported it after the disable


def test_the_pages_quit_disables_every_axis_and_ends_the_console(tmp_path):
    import json

    from websockets.sync.client import connect as ws_connect

    proc, url = start_ui(tmp_path, "--axis", "x")
    try:
        base, token = url.split("/?")[0], url.split("token=")[1]
        with ws_connect(base.replace("http", "ws") + f"/ws?token={token}") as ws:
            for rid, op in ((1, "enable"), (2, "quit")):
                ws.send(json.dumps({"id": rid, "op": op, "axis": "x"}))
                while (msg := json.loads(ws.recv(timeout=60)))["type"] != "reply":
                    pass
                assert msg["ok"], msg
        _out, err = proc.communicate(timeout=60)  # the page's Quit ends it: no signal sent
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "closed: x Switch On Disabled" in err


def test_listen_beyond_loopback_warns_and_a_bad_address_is_refused(tmp_path):
    proc, url = start_ui(tmp_path, "--axis", "x", "--listen", "0.0.0.0")
    try:
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "warning: serving on 0.0.0.0, beyond this computer" in err
    r = subprocess.run([sys.executable, "-m", "drivectl.tools.cli.main", "ui", "--listen", "my-laptop"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "drivectl: --listen: 'my-laptop' is not an IP address (e.g. 127.0.0.1, 0.0.0.0)"]
    r = subprocess.run([sys.executable, "-m", "drivectl.tools.cli.main", "ui", "--port", "70000"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--port" in r.stderr


def stop_ui(proc: subprocess.Popen) -> tuple[str, str]:
    try:
        proc.send_signal(signal.SIGINT)
        return proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()


def test_config_after_the_command_is_the_machine_served(tmp_path):
    from drivectl.machine.config import DEFAULT_CONFIG_TOML

    cfg = tmp_path / "machine.toml"
    cfg.write_text(DEFAULT_CONFIG_TOML.replace("[axes.x", "[axes.feed"))  # an axis the embedded one lacks
    proc, url = start_ui(tmp_path, "--config", str(cfg), "--axis", "feed")
    _out, err = stop_ui(proc)
    assert proc.returncode == 0, err
    assert "closed: feed Switch On Disabled" in err


@pytest.mark.parametrize("text, expect", [
    (None, "{cfg}: no such configuration file"),
    ("following_error_m = 0.001", "{cfg}: axes.x.limits.following_error_m: must be > 0, got -1"),
    ('controller = "mbc"', "{cfg}: axes.x.controller: unknown controller 'mbcx'"),
])
def test_a_bad_config_is_one_line_naming_file_and_field_exit_2_before_anything(tmp_path, text, expect):
    from drivectl.machine.config import DEFAULT_CONFIG_TOML

    cfg = tmp_path / "machine.toml"
    if text is not None:
        bad = {"following_error_m = 0.001": "following_error_m = -1", 'controller = "mbc"': 'controller = "mbcx"'}
        cfg.write_text(DEFAULT_CONFIG_TOML.replace(text, bad[text], 1))
    r = subprocess.run([*UI, "--config", str(cfg), "--port", "0", "--out", str(tmp_path / "traces")],
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("drivectl: " + expect.format(cfg=cfg)), r.stderr
    assert not (tmp_path / "traces").exists()  # nothing written, no bus opened


def test_a_port_in_use_is_one_line_exit_2(tmp_path):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = subprocess.run([*UI, "--port", str(port), "--out", str(tmp_path / "traces")], capture_output=True,
                           text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        f"drivectl: --port/--listen: cannot serve on 127.0.0.1:{port}: Address already in use"]


def test_open_without_a_display_says_so_in_one_line_and_keeps_serving(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "BROWSER")}
    proc, url = start_ui(tmp_path, "--axis", "x", "--open", env=env)
    try:
        line = proc.stderr.readline()
        assert line.startswith("drivectl: --open: no display here (DISPLAY and WAYLAND_DISPLAY unset)"), line
        assert get(url)[0] == 200  # still serving
    finally:
        _out, err = stop_ui(proc)
    assert proc.returncode == 0 and "closed: x Switch On Disabled" in err


def test_open_hands_the_url_to_the_browser(tmp_path):
    browser = tmp_path / "browser"
    browser.write_text('#!/bin/sh\necho "browser got $1"\n')
    browser.chmod(0o755)
    proc, url = start_ui(tmp_path, "--axis", "x", "--open", env={**os.environ, "DISPLAY": ":99",
                                                                   "BROWSER": str(browser)})
    try:
        lines = [proc.stdout.readline() for _ in range(2)]  # the Ctrl-C line, then the browser's
        assert lines[1].strip() == f"browser got {url}", lines
    finally:
        _out, err = stop_ui(proc)
    assert proc.returncode == 0, err


def test_bad_input_is_refused_with_one_line_and_nothing_moves(tmp_path):
    from drivectl.tools.ui.console import USER_ERRORS

    with running_console(tmp_path / "traces", axes=("x",)) as (console, _web, _url):
        console.command("t", {"op": "enable", "axis": "x"})
        x = console.m.axes["x"]
        before = x.position
        for msg, expect in (
                ({"op": "move_to", "axis": "x", "position": "20"}, "needs a unit"),
                ({"op": "move_to", "axis": "x", "position": "20 furlongs"}, "unit 'furlongs'"),
                ({"op": "move_to", "axis": "x", "position": "9m"}, "outside the soft limits"),
                ({"op": "move_to", "axis": "x", "position": "2mm", "speed": "-1mm/s"}, "not within"),
                ({"op": "move_by", "axis": "x", "distance": "nan mm"}, "distance"),
                ({"op": "jog", "axis": "x", "direction": 1, "speed": "9m/s"}, "max_velocity_m_s"),
                ({"op": "jog", "axis": "x", "direction": 2}, "direction"),
                ({"op": "move_to", "axis": "w", "position": "1mm"}, "not on this machine"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "trigger": "level",
                  "level_channel": "position", "level": "3 parsecs"}, "trigger level"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "pre": "9s"}, "longer than the ring"),
                ({"op": "teleport"}, "unknown request"),
                # every field of a move: the value, its unit and kind, the axis's soft and motion limits
                ({"op": "move_to", "axis": "x"}, "position"),
                ({"op": "move_to", "axis": "x", "position": "5mm/s"}, "position"),
                ({"op": "move_by", "axis": "x", "distance": "500mm"}, "outside the soft limits"),
                ({"op": "move_by", "axis": "x", "distance": "-0.2m"}, "outside the soft limits"),
                ({"op": "move_to", "axis": "x", "position": "2mm", "speed": "0mm/s"}, "not within"),
                ({"op": "move_to", "axis": "x", "position": "2mm", "speed": "5mm"}, "speed"),
                ({"op": "move_by", "axis": "x", "distance": "1mm", "speed": "3m/s"}, "max_velocity_m_s"),
                # a jog: its speed (unit, > 0, within max_velocity_m_s) and direction
                ({"op": "jog", "axis": "x", "direction": 1, "speed": "fast"}, "jog speed"),
                ({"op": "jog", "axis": "x", "direction": -1, "speed": "-5mm/s"}, "not within"),
                ({"op": "jog", "axis": "y", "direction": 1}, "not on this machine"),
                # a capture: channels, trigger, pre/post, and a level trigger's channel, direction, level
                ({"op": "capture", "axis": "x", "channels": []}, "at least one channel"),
                ({"op": "capture", "axis": "x", "channels": ["phase"]}, "channel 'phase'"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "trigger": "position>0.002"},
                 "expected now, move, fault or level"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "pre": "-1s"}, ">= 0 s"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "post": "2mm"}, "post"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "trigger": "level",
                  "level_channel": "phase", "level": "1"}, "trigger channel 'phase'"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "trigger": "level",
                  "level_channel": "velocity", "level": "3mm"}, "trigger level"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "trigger": "level",
                  "level_channel": "effort", "level": "5mm"}, "not a number"),
                ({"op": "capture", "axis": "x", "channels": ["position"], "trigger": "level",
                  "level_channel": "position", "level": "2mm", "direction": "sideways"}, "direction")):
            with pytest.raises(USER_ERRORS, match=expect) as exc:
                console.command("t", msg)
            assert "\n" not in str(exc.value)
            assert console.capture is None and console.jogs == {}  # nothing armed, nothing held
        assert console.m.status()["axes"]["x"]["move"] is None and abs(x.position - before) < 5e-6
        # the scope's subscription: an unknown axis or channel, a window that is not > 0
        from drivectl.tools.ui.stream import ScopeFeed

        feed = ScopeFeed(console.m)
        for args, expect in ((("w", ["position"], 5.0), "not on this machine"), (("x", ["phase"], 5.0), "'phase'"),
                             (("x", ["position"], 0.0), "window must be > 0")):
            with pytest.raises(ValueError, match=expect):
                feed.subscribe(*args)
        assert feed.axis is None


def test_the_scope_feed_reads_only_new_samples_from_the_ring():
    from drivectl.controllers.runtime.capture import Ring
    from drivectl.tools.ui.console import standstill_cycle
    from drivectl.tools.ui.stream import read_since

    ring = Ring(100)
    for k in range(250):
        ring.push(k, k * 1e-3, 0.0, 0.0, 0.0, 0.0, 0)
    data, cycles = read_since(ring, -1, 50)
    assert cycles.tolist() == list(range(199, 249))  # the newest sample (249) is left for the next read
    assert np.allclose(data[0], cycles * 1e-3)
    data, cycles = read_since(ring, 240, 1000)
    assert cycles.tolist() == list(range(241, 249))
    # the reference ramps to cycle 230 then holds: at rest from 230 on
    ring = Ring(100)
    for k in range(300):
        ring.push(k, min(k, 230) * 1e-3, 0.0, 0.0, 0.0, 0.0, 0)
    assert standstill_cycle(ring, 220) == 230


def test_the_conductor_paces_simulated_time_to_its_clock_and_never_races_ahead(tmp_path):
    """On a clock the test moves by hand: simulated time follows it a tick at a time, never runs ahead of
    it, and after a jump (load, a long command) goes on from there instead of rushing to catch up."""
    import drivectl
    from drivectl.tools.ui.console import Conductor

    now = [100.0]
    m = drivectl.connect(machine_config(), axes=["x"], fault_dir=tmp_path)
    c0 = m.loop.cycle  # lockstep: no cycle runs but those the conductor asks for
    c = Conductor(m, tick_s=0.01, clock=lambda: now[0]).start()

    def settled(at_least: int) -> int:
        """The loop's cycles once the conductor has run ``at_least`` of them (then it waits for the clock)."""
        while c.call(lambda: m.loop.cycle).result(60) - c0 < at_least:
            pass
        return c.call(lambda: m.loop.cycle).result(60) - c0

    try:  # in cycles of 1 ms, ticks of 10: simulated time reaches the clock and is at most a tick ahead
        assert settled(1) == 10  # the clock stands: one tick, no more
        now[0] += 0.2
        assert 200 <= settled(200) <= 210
        got = settled(200)
        now[0] += 10.0  # far behind (more than 0.25 s): it goes on from now, a tick at a time, no rush
        assert settled(got + 1) == got + 10
        now[0] += 0.1
        assert got + 100 <= settled(got + 100) <= got + 110
    finally:
        c.stop()
        m.close()


def test_a_jog_release_stops_in_the_next_cycle_and_a_late_renewal_does_not_restart_it(tmp_path):
    """Lockstep, at the console's level: x jogged at 5 mm/s from one client; its release starts the stop at
    once, and a renewal that arrives after the release (one sent before it, or a timer that fired late)
    is ignored: from the release to standstill the reference goes no further than the stop's own
    distance plus 2 cycles' travel. A new press afterwards jogs again."""
    import drivectl
    from drivectl.tools.ui.console import Console, standstill_cycle

    m = drivectl.connect(machine_config(), axes=["x"], fault_dir=tmp_path)
    console = Console(m, tmp_path)  # no conductor: this test runs the cycles
    try:
        x = m.axes["x"]
        x.enable()
        rt, loop = m.loop.axes["x"], m.loop
        jog = {"op": "jog", "axis": "x", "direction": 1, "speed": "5mm/s", "press": 1}
        assert "held" in console.command("web-1", jog)
        for _ in range(10):  # held for 0.5 s, renewed every 50 ms
            loop.step(50)
            console.command("web-1", jog)
        v = 5e-3
        assert rt.traj.velocity == pytest.approx(v, rel=1e-6)
        released_at, ref0 = loop.cycle, rt.traj.position
        assert "jog ended" in console.command("web-1", {"op": "jog_release", "axis": "x", "press": 1})
        loop.step(1)
        assert 0 < rt.traj.velocity < v  # the controlled stop began in the next cycle
        loop.step(2)
        assert console.command("web-1", jog) == ""  # the late renewal: ignored, no new jog
        loop.step(5)
        console.command("web-1", jog)
        loop.step(300)
        console.watch()
        assert rt.handle is None or rt.handle.kind == "stop"
        rest = standstill_cycle(rt.ring, released_at)
        assert rest is not None and rest - released_at < 100  # well inside the 200-cycle dead man
        dt = loop.dt
        travelled = rt.traj.position - ref0
        bound = stop_distance(v, rt.motion) + 2 * v * dt
        assert 0 < travelled <= bound, (travelled, bound)
        print(f"release to standstill: {travelled * 1e6:.1f} um in {(rest - released_at) * dt * 1e3:.0f} ms "
              f"(bound {bound * 1e6:.1f} um)")
        ev = console.jog_log[-1]
        assert ev["why"] == "release" and ev["stop_cycle"] == released_at
        assert 0 < ev["travel_after_stop_m"] <= bound and ev["standstill_after_stop_s"] == (rest - released_at) * dt
        assert "x" not in console.jogs
        # a new press (its own id) jogs again
        assert "held" in console.command("web-1", dict(jog, press=2))
        loop.step(100)
        assert rt.traj.velocity == pytest.approx(v, rel=1e-6)
        console.command("web-1", {"op": "jog_release", "axis": "x", "press": 2})
        loop.step(200)
    finally:
        m.close()
