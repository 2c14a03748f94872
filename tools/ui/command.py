"""``drivectl ui``: the commissioning console in a browser, on one connected machine.

Loopback only unless ``--listen`` says otherwise (with a warning); the URL printed at start carries a
random token that every request needs. Ctrl-C, SIGTERM or the page's Quit disable every axis
(verified from the drives) and leave, as the shell does. The web stack is the optional extra
``pip install 'drivectl[ui]'``; without it the command says so and exits 2 before connecting.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import signal
import socket
import sys
import threading
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

LOOPBACK = "127.0.0.1"
DEFAULT_PORT = 8765


def add_ui_parser(sub: Any) -> None:
    s = sub.add_parser("ui", help="the commissioning console in a browser (pip install 'drivectl[ui]')",
                       description="Serve a local web console on the machine: power, jog, moves, homing, a live "
                       "scope with triggers, the trace folder and explain. Prints a URL with a token; Ctrl-C "
                       "disables every axis (verified) and leaves.")
    # also after the command (`drivectl ui --config FILE`); SUPPRESS keeps a --config given before it
    s.add_argument("--config", metavar="FILE", default=argparse.SUPPRESS,
                   help="machine configuration TOML (as `drivectl --config FILE ui`)")
    s.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT}; 0: any free)")
    s.add_argument("--listen", default=LOOPBACK, metavar="ADDRESS",
                   help="address to serve on (default 127.0.0.1, this computer only; any other is reachable "
                   "from the network: a warning is printed)")
    s.add_argument("--open", action="store_true", help="open the URL in the default browser")
    s.add_argument("--axis", default=None, help="axes to connect (default: every axis of the configuration)")
    s.add_argument("--clock", choices=("lockstep", "wall"), default=None,
                   help="the loop's clock (default: lockstep, paced to the wall clock, on the emulated drives; "
                   "wall on a real bus)")
    s.add_argument("--sim", action="store_true", help="SimAxis (the plants with no bus)")
    from drivectl.tools.cli.shell import add_loop_flag

    add_loop_flag(s)
    s.add_argument("--out", default="traces", metavar="DIR", help="the trace folder: scope saves, explain's output")
    s.add_argument("--store", metavar="DIR", help="the Health page's store (default: [health] store in the "
                   "configuration, else the user's data folder; docs/health.md)")


def check_listen(address: str, port: int) -> tuple[str, bool]:
    """(address, is loopback); ValueError naming the flag for a bad one."""
    if not 0 <= port <= 65535:
        raise ValueError(f"--port: expected 0..65535, got {port}")
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        if address != "localhost":
            raise ValueError(f"--listen: {address!r} is not an IP address (e.g. 127.0.0.1, 0.0.0.0)") from None
        return LOOPBACK, True
    return address, ip.is_loopback


def bind(address: str, port: int) -> socket.socket:
    """The listening socket, bound before the machine is connected (a port in use fails first)."""
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((address, port))
    except OSError as exc:
        sock.close()
        raise ValueError(f"--port/--listen: cannot serve on {address}:{port}: {exc.strerror}") from None
    sock.listen(64)
    sock.set_inheritable(True)
    return sock


def url_of(sock: socket.socket, token: str, loopback: bool) -> str:
    host, port = sock.getsockname()[:2]
    if host in ("0.0.0.0", "::"):
        host = socket.gethostname()
    if ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{port}/?token={token}"


def open_browser(url: str, environ: dict[str, str] | None = None) -> str | None:
    """``--open``: the URL handed to the default browser from a thread (a browser that blocks until it is
    closed never holds the console up). Returns the one line to print when no browser can be opened
    here (no display, none found); the console serves on either way."""
    import webbrowser

    env = os.environ if environ is None else environ
    if sys.platform not in ("darwin", "win32") and not (env.get("DISPLAY") or env.get("WAYLAND_DISPLAY")):
        port = urlsplit(url).port
        return (f"--open: no display here (DISPLAY and WAYLAND_DISPLAY unset): open the URL above in a browser "
                f"(from another computer: ssh -L {port}:127.0.0.1:{port} {socket.gethostname()})")
    try:
        browser = webbrowser.get()
    except webbrowser.Error:
        return "--open: no web browser found here: open the URL above in one"

    def run() -> None:
        try:
            opened = browser.open(url)
        except OSError as exc:
            opened, why = False, str(exc)
        else:
            why = "it reported a failure"
        if not opened:
            print(f"drivectl: --open: the browser did not open ({why}): open the URL above in one",
                  file=sys.stderr, flush=True)

    threading.Thread(target=run, name="drivectl-ui-open", daemon=True).start()
    return None


def make_server(web: Any) -> Any:
    """A uvicorn server for the web console; the page's Quit ends it."""
    import uvicorn

    config = uvicorn.Config(web.app, log_level="warning", lifespan="off", ws="websockets-sansio",
                            timeout_graceful_shutdown=2)
    server = uvicorn.Server(config)

    def quit_() -> None:
        server.should_exit = True

    web.on_quit = quit_
    return server


def start_in_thread(web: Any, sock: socket.socket) -> tuple[Any, threading.Thread]:
    """Serve ``web`` on ``sock`` from a thread (tests; programs that embed the console): returns the
    server (``should_exit = True`` ends it) and the thread, once the server accepts connections."""
    import asyncio

    server = make_server(web)
    thread = threading.Thread(target=lambda: asyncio.run(server.serve(sockets=[sock])), name="drivectl-ui-server",
                              daemon=True)
    thread.start()
    for _ in range(500):
        if server.started or not thread.is_alive():
            break
        threading.Event().wait(0.01)
    if not server.started:
        raise RuntimeError("drivectl ui: the web server did not start")
    return server, thread


def cmd_ui(args: Any) -> int:
    try:
        import starlette  # noqa: F401 - present or the extra is missing
        import uvicorn  # noqa: F401
        import websockets  # noqa: F401
    except ImportError as exc:
        print(f"drivectl: ui needs the web console's extra ({exc.name} is missing): pip install 'drivectl[ui]'",
              file=sys.stderr)
        return 2
    from drivectl.machine.config import load_config
    from drivectl.session import connect
    from drivectl.tools.cli.checks import check_output_folder, parse_axes
    from drivectl.tools.ui.console import Console
    from drivectl.tools.ui.server import WebConsole, plotly_js

    try:
        address, loopback = check_listen(args.listen, args.port)
    except ValueError as exc:
        print(f"drivectl: {exc}", file=sys.stderr)
        return 2
    if plotly_js() is None:
        print("drivectl: ui needs plotly (its wheel carries the plotting JavaScript): pip install 'drivectl[ui]'",
              file=sys.stderr)
        return 2
    # the configuration first: a bad file or field is one line (exit 2) before any folder, socket or bus
    cfg = load_config(args.config)
    axes = parse_axes(args.axis) if args.axis else None
    for name in axes or ():
        cfg.axis(name)
    out = check_output_folder(args.out, "--out")
    try:
        sock = bind(address, args.port)
    except ValueError as exc:
        print(f"drivectl: {exc}", file=sys.stderr)
        return 2
    machine = connect(cfg, axes=axes, clock=args.clock, sim=args.sim, fault_dir=out, loop=args.loop)
    console = Console(machine, Path(out), health_store=Path(args.store).expanduser() if args.store else None)
    web = WebConsole(console)
    server = make_server(web)
    states: dict[str, str] = {}

    def terminate(signum: int, frame: object) -> None:  # noqa: ARG001 - leave through the finally below
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, terminate)  # uvicorn re-raises the SIGTERM it caught: it ends here
    try:
        console.start()
        url = url_of(sock, web.token, loopback)
        print(f"drivectl ui on {machine.bus}: axes {', '.join(machine.axes)} ({machine.clock})")
        if not loopback:
            print(f"warning: serving on {address}, beyond this computer: anyone who can reach port "
                  f"{sock.getsockname()[1]} and has this URL can move the axes", file=sys.stderr)
        print(f"open {url}")
        print("Ctrl-C here (or Quit on the page) disables every axis, verified, and leaves", flush=True)
        if args.open:  # the socket listens already: the browser's first request waits for the server
            why = open_browser(url)
            if why:
                print(f"drivectl: {why}", file=sys.stderr, flush=True)
        server.run(sockets=[sock])
    except KeyboardInterrupt:  # uvicorn re-raises the Ctrl-C it caught, once it has shut down; one that came
        pass  # before its handler was in place (the URL is out, a script sends SIGINT at once) ends it the same
    finally:
        signal.signal(signal.SIGTERM, old)
        states = console.close()
        sock.close()
        if states:  # what each drive reported last, as the shell says it
            live = ("Operation Enabled", "Quick Stop Active", "unknown")
            print("closed: " + ", ".join(f"{n} {s}" + (" (not confirmed: it may still be powered)" if s in live
                                                       else "") for n, s in states.items()), file=sys.stderr)
    return 0
