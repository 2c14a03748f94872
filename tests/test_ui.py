"""Issue 28 points 1, 3, 5 without a browser: ``drivectl ui`` as a process (URL with a token, loopback,
--listen's warning, Ctrl-C disables every axis), the console's validation, and the ring read."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from ui_helpers import get, machine_config, running_console, ui_stack_or_skip

ui_stack_or_skip()


def start_ui(tmp_path, *extra: str) -> tuple[subprocess.Popen, str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "drivectl.tools.cli.main", "ui", "--port", "0", "--out",
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
                ({"op": "teleport"}, "unknown request")):
            with pytest.raises(USER_ERRORS, match=expect) as exc:
                console.command("t", msg)
            assert "\n" not in str(exc.value)
        assert console.m.status()["axes"]["x"]["move"] is None and abs(x.position - before) < 5e-6


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


def test_the_conductor_paces_simulated_time_to_the_wall_clock_and_never_races_ahead(tmp_path):
    import drivectl
    from drivectl.tools.ui.console import Conductor

    m = drivectl.connect(machine_config(), axes=["x"], fault_dir=tmp_path)
    c = Conductor(m).start()
    try:
        t0, c0 = time.monotonic(), m.loop.cycle
        time.sleep(0.3)
        sim = (m.loop.cycle - c0) * m.loop.dt
        wall = time.monotonic() - t0
        assert sim <= wall + 0.02  # never ahead of the wall clock (it may lag under load)
        assert c.call(lambda: m.loop.cycle).result(30) >= c0
    finally:
        c.stop()
        m.close()
