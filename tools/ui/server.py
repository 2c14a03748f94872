"""The console's web app (Starlette): the page, its static files, the plotting library from its own
installed package, the trace folder, and one websocket per page for status, scope data and commands.

Every request and every websocket carries the console's token (the URL printed at start; the page sets
a same-site cookie so that its own static files and the websocket carry it too). Without it: 403.
The status and scope data are read from what the loop already keeps (its status counters and the
axes' ring buffers, tools/ui/stream.py): the cycle does no work for the console.
"""

from __future__ import annotations

import asyncio
import importlib.util
import itertools
import json
import os
import secrets
import sys
import time
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, HTMLResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from drivectl.tools.ui import traces
from drivectl.tools.ui.console import USER_ERRORS, Console, finite
from drivectl.tools.ui.stream import ScopeFeed, capture_payload

STATIC = Path(__file__).resolve().parent / "static"
COOKIE = "drivectl_ui"
#: how often the page gets the machine's status and the scope's new samples (s)
PUSH_S = 0.1
DEBUG = bool(os.environ.get("DRIVECTL_UI_DEBUG"))


def plotly_js() -> Path | None:
    """plotly.min.js as the plotly wheel installs it (package_data), without importing plotly."""
    spec = importlib.util.find_spec("plotly")
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        path = Path(root) / "package_data" / "plotly.min.js"
        if path.is_file():
            return path
    return None


class WebConsole:
    """The app around one :class:`Console`; ``app`` is the ASGI application."""

    def __init__(self, console: Console, token: str | None = None):
        self.console = console
        self.token = token or secrets.token_urlsafe(24)
        self.on_quit: Any = None  # the runner's: ends the server (then every axis is disabled)
        self._clients = itertools.count(1)
        self.app = Starlette(routes=[
            Route("/", self.index),
            Route("/static/{name}", self.static),
            Route("/api/status", self.api_status),
            Route("/api/jogs", self.api_jogs),
            Route("/api/traces", self.api_traces),
            Route("/api/margins", self.api_margins),
            Route("/api/trace", self.api_trace),
            Route("/api/explain", self.api_explain, methods=["POST"]),
            Route("/api/health", self.api_health),
            Route("/api/health/axis", self.api_health_axis),
            Route("/api/health/analyze", self.api_health_analyze, methods=["POST"]),
            Route("/files/{name:path}", self.files),
            WebSocketRoute("/ws", self.websocket),
        ])

    # -- the token ---------------------------------------------------------------------------------------------
    def _authorized(self, conn: Request | WebSocket) -> bool:
        given = conn.query_params.get("token") or conn.cookies.get(COOKIE) or ""
        return secrets.compare_digest(given.encode(), self.token.encode())

    def _refused(self) -> Response:
        return PlainTextResponse("drivectl ui: a valid token is required (open the URL the console printed)",
                                 status_code=403)

    # -- pages and files ---------------------------------------------------------------------------------------
    async def index(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        resp = HTMLResponse((STATIC / "index.html").read_text())
        resp.set_cookie(COOKIE, self.token, httponly=True, samesite="strict")
        return resp

    async def static(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        name = request.path_params["name"]
        if name == "plotly.min.js":
            path = plotly_js()
            if path is None:
                return PlainTextResponse("plotly is not installed: pip install 'drivectl[ui]'", status_code=404)
            return FileResponse(path, media_type="text/javascript")
        path = STATIC / name
        if "/" in name or not path.is_file():
            return PlainTextResponse("not found", status_code=404)
        return FileResponse(path)

    async def files(self, request: Request) -> Response:
        """A file of the output folder (a trace, a PNG of a capture or of explain)."""
        if not self._authorized(request):
            return self._refused()
        try:
            path = traces.inside(self.console.out, request.path_params["name"])
        except ValueError as exc:
            return PlainTextResponse(str(exc), status_code=404)
        return FileResponse(path)

    async def api_status(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        return JSONResponse(self.status())

    async def api_jogs(self, request: Request) -> Response:
        """How every jog ended: the cycle of its last renewal, of its stop, of its standstill."""
        if not self._authorized(request):
            return self._refused()
        self.console.watch()
        return JSONResponse(finite(self.console.jog_log))

    async def api_traces(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        return JSONResponse(traces.listing(self.console.out))

    async def api_margins(self, request: Request) -> Response:
        """The last `bode --loop open` figure and margins per axis in the output folder (the Axis page)."""
        if not self._authorized(request):
            return self._refused()
        return JSONResponse(finite(traces.margin_figures(self.console.out)))

    async def api_trace(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        try:
            got = await asyncio.to_thread(traces.load, self.console.out, request.query_params.get("name", ""))
        except (ValueError, OSError) as exc:
            return JSONResponse({"error": str(exc)}, status_code=400)
        return JSONResponse(finite(got))

    async def api_explain(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        body = await request.json()
        try:
            got = await traces.run_explain(self.console, str(body.get("name", "")), str(body.get("plant", "")))
        except ValueError as exc:
            return JSONResponse({"error": str(exc)}, status_code=400)
        return JSONResponse(got)

    # -- the Health page (tools/ui/health.py) ------------------------------------------------------------------
    async def api_health(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        try:
            got = await asyncio.to_thread(self.console.health.fleet)
        except ValueError as exc:
            return JSONResponse({"error": str(exc)}, status_code=400)
        return JSONResponse(finite({**got, **self.console.health.status()}))

    async def api_health_axis(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        q = request.query_params
        try:
            got = await asyncio.to_thread(self.console.health.axis, q.get("machine", ""), q.get("axis", ""))
        except ValueError as exc:
            return JSONResponse({"error": str(exc)}, status_code=400)
        return JSONResponse(finite(got))

    async def api_health_analyze(self, request: Request) -> Response:
        if not self._authorized(request):
            return self._refused()
        try:
            got = await self.console.health.analyze()
        except ValueError as exc:
            return JSONResponse({"error": str(exc)}, status_code=400)
        return JSONResponse(got)

    # -- the machine's state -------------------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        c = self.console
        c.watch()
        st = c.m.status()
        for name, a in st["axes"].items():
            a["drive_error"] = c.drive_errors.get(name, "")
            a["jog_held"] = name in c.jogs
            ax = c.m.axes[name]
            lim = ax.limits.position
            a["soft_limits_m"] = list(lim) if lim is not None else None
            a["max_velocity_m_s"] = ax.motion_limits.max_velocity
            a["jog_deadman_s"] = ax.motion_limits.jog_deadman
        cap = c.capture
        st["console"] = {"capture": None if cap is None else {"axis": cap.axis, "state": cap.state,
                                                              "seq": c.capture_seq, "detail": cap.detail},
                         "saved": [p.name for p in c.saved[-4:]], "time_s": c.m.loop.cycle * c.m.loop.dt,
                         "axis_names": list(c.m.axes), "health": c.health.status()}
        return finite(st)

    # -- the websocket: status and scope out, commands in ---------------------------------------------------------
    async def websocket(self, ws: WebSocket) -> None:
        if not self._authorized(ws):
            await ws.close(code=1008)
            return
        await ws.accept()
        client = f"c{next(self._clients)}"
        if DEBUG:
            print(f"drivectl ui: connection {client} open", file=sys.stderr)
        feed = ScopeFeed(self.console.m)
        pusher = asyncio.create_task(self._push(ws, feed))

        async def reply(rid: Any, ok: bool, message: str, **extra: Any) -> None:
            await ws.send_text(json.dumps({"type": "reply", "id": rid, "ok": ok, "message": message, **extra}))

        try:
            while True:
                msg = json.loads(await ws.receive_text())
                rid, op = msg.get("id"), msg.get("op")
                if op == "scope":
                    try:
                        feed.subscribe(str(msg.get("axis")), [str(c) for c in msg.get("channels") or ()],
                                       float(msg.get("window_s") or 5.0))
                    except ValueError as exc:
                        await reply(rid, False, str(exc))
                    continue
                if op == "save":
                    try:
                        written = await asyncio.to_thread(self.console.save_capture)
                    except USER_ERRORS as exc:
                        await reply(rid, False, str(exc))
                        continue
                    await reply(rid, True, "wrote " + ", ".join(p.name for p in written),
                                files=[p.name for p in written])
                    continue
                if op == "quit":
                    await reply(rid, True, "closing: every axis is disabled, verified from the drives")
                    if self.on_quit is not None:
                        self.on_quit()
                    continue
                try:
                    if op in ("jog", "jog_release", "stop", "stop_all"):  # at once, never behind other commands
                        line = self.console.command(client, msg)
                    else:
                        line = await asyncio.to_thread(self.console.command, client, msg)
                except USER_ERRORS as exc:
                    await reply(rid, False, str(exc))
                    continue
                if line or op != "jog":
                    await reply(rid, True, line)
        except WebSocketDisconnect:
            pass
        except Exception as exc:  # noqa: BLE001 - say why this page lost its connection; the console goes on
            print(f"drivectl ui: connection {client} closed: {type(exc).__name__}: {exc}", file=sys.stderr)
        finally:
            if DEBUG:
                print(f"drivectl ui: connection {client} closed", file=sys.stderr)
            pusher.cancel()
            self.console.client_gone(client)

    async def _push(self, ws: WebSocket, feed: ScopeFeed) -> None:
        last_capture = None
        try:
            while True:
                t0 = time.monotonic()
                await ws.send_text(json.dumps({"type": "status", "status": self.status()}))
                chunk = feed.poll()
                if chunk is not None:
                    await ws.send_text(json.dumps(finite(chunk)))
                cap = self.console.capture
                if cap is not None and cap.done and cap is not last_capture:
                    last_capture = cap
                    if cap.state == "done":
                        await ws.send_text(json.dumps(finite(capture_payload(cap))))
                await asyncio.sleep(max(0.01, PUSH_S - (time.monotonic() - t0)))
        except (WebSocketDisconnect, RuntimeError, asyncio.CancelledError):
            return
        except Exception as exc:  # noqa: BLE001 - a bug in the stream: say it, keep the console (and the loop) up
            print(f"drivectl ui: status stream ended: {type(exc).__name__}: {exc}", file=sys.stderr)
