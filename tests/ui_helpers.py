"""The web console for tests: a connected machine (lockstep, paced), the server in a thread, and a headless
Debian chromium driven by selenium (skipped, with the reason, where either is missing)."""

from __future__ import annotations

import json
import math
import os
import shutil
import tomllib
import urllib.error
import urllib.request
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

CHROME_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-dev-shm-usage", "--window-size=1400,1000")


def ui_stack_or_skip() -> None:
    for mod in ("starlette", "uvicorn", "websockets", "plotly"):
        pytest.importorskip(mod, reason=f"{mod} is not installed (pip install '.[ui]')")


def browser_or_skip() -> tuple[str, str]:
    pytest.importorskip("selenium", reason="selenium is not installed (pip install '.[test]')")
    chrome = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chrome or not driver:
        pytest.skip("no chromium + chromedriver here (apt-get install chromium chromium-driver; .ci/run does)",
                    allow_module_level=True)
    return chrome, driver


def machine_config(**motion: float) -> Any:
    """The embedded machine as it is (x under its default controller), with ``motion`` on x and y."""
    from drivectl.machine.config import DEFAULT_CONFIG_TOML, parse_config

    data = tomllib.loads(DEFAULT_CONFIG_TOML)
    if motion:
        for name in ("x", "y"):
            data["axes"][name]["motion"] = dict(motion)
    return parse_config(data, "<test>")


@contextmanager
def running_console(out: Path, *, axes: tuple[str, ...] = ("x", "y"), faults: list[str] | None = None,
                    **motion: float):
    """(console, web, url): a lockstep machine paced to the wall clock, served on a free loopback port."""
    import drivectl
    from drivectl.tools.ui.command import bind, start_in_thread, url_of
    from drivectl.tools.ui.console import Console
    from drivectl.tools.ui.server import WebConsole

    out.mkdir(parents=True, exist_ok=True)
    m = drivectl.connect(machine_config(**motion), axes=list(axes), fault_dir=out, faults=faults)
    console = Console(m, out)
    sock = bind("127.0.0.1", 0)
    server = thread = None
    try:
        console.start()
        web = WebConsole(console)
        server, thread = start_in_thread(web, sock)
        yield console, web, url_of(sock, web.token, True)
    finally:
        if server is not None:
            server.should_exit = True
            thread.join(10)
        sock.close()
        states = console.close()
        assert all(s not in ("Operation Enabled", "Quick Stop Active") for s in states.values()), states


def get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def get_json(base: str, path: str, token: str) -> Any:
    code, body = get(f"{base}{path}?token={token}")
    assert code == 200, body
    return json.loads(body)


def make_driver(chrome: str, driver_path: str, profile: Path) -> Any:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chrome
    for f in CHROME_FLAGS:
        opts.add_argument(f)
    opts.add_argument(f"--user-data-dir={profile}")
    os.environ.setdefault("SE_OFFLINE", "true")  # never let selenium fetch a driver: Debian's is given
    from selenium.common.exceptions import SessionNotCreatedException

    for attempt in range(3):  # a loaded machine can miss chromedriver's start-up deadline: try again
        try:
            return webdriver.Chrome(service=Service(executable_path=driver_path), options=opts)
        except SessionNotCreatedException:
            if attempt == 2:
                raise
    raise AssertionError("unreachable")


def stop_distance(v: float, motion: Any) -> float:
    """The controlled stop's own distance from ``v`` under the axis's motion limits (its deceleration and
    jerk: a jerk-limited stop from 5 mm/s does not reach max_acceleration)."""
    a, j = motion.max_acceleration, motion.max_jerk
    v = abs(v)
    if v * j <= a * a:  # the deceleration peaks at sqrt(v j) < a: two jerk phases of sqrt(v/j) each
        return v * math.sqrt(v / j)
    return v * v / (2 * a) + v * a / (2 * j)

