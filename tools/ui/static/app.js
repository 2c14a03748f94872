// drivectl console: one websocket for status, scope data and commands (docs/ui.md).
"use strict";

const CHANNELS = ["reference", "position", "following_error", "effort", "velocity", "torque", "statusword"];
// display unit per channel: [group, scale, unit]; one y axis per group
const UNIT = {
  reference: ["pos", 1e3, "mm"], position: ["pos", 1e3, "mm"], following_error: ["err", 1e6, "µm"],
  velocity: ["vel", 1e3, "mm/s"], effort: ["eff", 1, ""], torque: ["eff", 1, ""], statusword: ["sw", 1, ""],
};
const COLUMN_CHANNEL = { ref_m: "reference", pos_m: "position", following_error_m: "following_error",
  effort: "effort", vel_m_s: "velocity", torque_actual: "torque", statusword: "statusword" };

const ui = {
  ws: null, ids: 0, pending: {}, status: null, axes: [], built: false,
  jog: null, scope: { live: true, t: [], ch: {}, frozen: null, cursors: [], channels: [], axis: null },
  trace: null, connected: false,
};
window.__drivectl = ui;  // for tests and the curious: the page's state

const $ = (sel) => document.querySelector(sel);
const tid = (id) => document.querySelector(`[data-testid="${id}"]`);
function el(tag, attrs = {}, ...kids) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "testid") e.dataset.testid = v; else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const k of kids) e.append(k);
  return e;
}
function say(text, error = false) {
  const m = $("#message");
  m.textContent = text;
  m.classList.toggle("error", error);
}
const token = new URLSearchParams(location.search).get("token") || "";
const withToken = (path) => path + (path.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token);

// ---------------------------------------------------------------------------------------------- connection
function note(what) { (ui.log = ui.log || []).push(`${(performance.now() / 1000).toFixed(2)} ${what}`); }
function connect() {
  note("connect");
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(`${proto}://${location.host}/ws?token=${encodeURIComponent(token)}`);
  ui.ws = ws;
  ws.onopen = () => {
    ui.connected = true;
    note("open");
    if (ui.closes) say("reconnected to the console");
    if (ui.scope.axis) subscribeScope();
  };
  ws.onclose = (ev) => {
    ui.connected = false;
    ui.closes = (ui.closes || 0) + 1;
    ui.lastClose = `code ${ev.code}${ev.reason ? " " + ev.reason : ""}`;
    note(`close ${ui.lastClose}`);
    jogStop("connection lost");
    say(`connection to the console lost (${ui.lastClose}): any jog stops by the dead man; reconnecting…`, true);
    setTimeout(connect, 1000);  // the console may be back (a dropped connection); a closed console stays closed
  };
  ws.onerror = () => note("error");
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.type === "status") onStatus(msg.status);
    else if (msg.type === "scope") onScope(msg);
    else if (msg.type === "capture") onCapture(msg);
    else if (msg.type === "reply") {
      const cb = ui.pending[msg.id];
      delete ui.pending[msg.id];
      if (msg.message) say(msg.message, !msg.ok);
      if (cb) cb(msg);
    }
  };
}
function send(op, args = {}, cb = null) {
  if (!ui.ws || ui.ws.readyState !== WebSocket.OPEN) { say("not connected to the console", true); return; }
  const id = ++ui.ids;
  if (cb) ui.pending[id] = cb;
  ui.ws.send(JSON.stringify({ id, op, ...args }));
}

// ---------------------------------------------------------------------------------------------- pages
function showPage(name) {
  for (const p of document.querySelectorAll(".page")) p.classList.toggle("hidden", p.id !== "page-" + name);
  for (const b of document.querySelectorAll("header nav button")) b.classList.toggle("active", b.dataset.page === name);
  if (name === "traces" || name === "explain") loadTraceList();
  if (name === "axis") loadMargins();
  if (name === "scope") {
    Plotly.Plots.resize("scope");
    if (ui.scope.live) requestScopeDraw();
  }
}
for (const b of document.querySelectorAll("header nav button")) b.addEventListener("click", () => showPage(b.dataset.page));

// Stop-all: the button and the space bar, on every page
function stopAll() { jogStop("stop-all"); send("stop_all"); }
$("#stop-all").addEventListener("click", stopAll);
document.addEventListener("keydown", (ev) => {
  if (ev.code === "Space" || ev.key === " ") { ev.preventDefault(); stopAll(); }
});
$("#quit").addEventListener("click", () => {
  jogStop("quit");
  send("quit");
});

// ---------------------------------------------------------------------------------------------- status
const fmt = (v, digits) => (v === null || v === undefined ? "–" : Number(v).toFixed(digits));
function buildAxes(names) {
  const body = $("#axes-table tbody");
  body.replaceChildren();
  const cards = $("#axis-cards");
  cards.replaceChildren();
  for (const n of names) {
    body.append(el("tr", {},
      el("td", {}, n), el("td", { testid: `state-${n}` }), el("td", { testid: `power-${n}` }),
      el("td", { class: "num", testid: `position-${n}` }), el("td", { class: "num", testid: `ferror-${n}` }),
      el("td", { class: "num", testid: `effort-${n}` }), el("td", { testid: `move-${n}` }),
      el("td", { class: "fault", testid: `fault-${n}` }),
      el("td", {}, el("button", { testid: `fault-reset-${n}`, onclick: () => send("fault_reset", { axis: n }) },
        "Fault reset"))));
    const inp = (id, value, size = 9) => el("input", { testid: `${id}-${n}`, value, size });
    const btn = (id, text, fn) => el("button", { testid: `${id}-${n}`, onclick: fn }, text);
    const val = (id) => tid(`${id}-${n}`).value;
    const jogBtn = (dir) => {
      const b = el("button", { class: "jog", testid: `jog-${dir > 0 ? "plus" : "minus"}-${n}` }, dir > 0 ? "▶ +" : "− ◀");
      b.addEventListener("pointerdown", (ev) => { ev.preventDefault(); jogStart(n, dir, b); });
      for (const e of ["pointerup", "pointerleave", "pointercancel", "lostpointercapture"]) {
        b.addEventListener(e, () => jogStop("release"));
      }
      b.addEventListener("contextmenu", (ev) => ev.preventDefault());
      return b;
    };
    cards.append(el("div", { class: "card" },
      el("h3", {}, `axis ${n} `, el("span", { class: "tag", testid: `axis-power-${n}` })),
      el("div", { class: "line" }, btn("enable", "Enable", () => send("enable", { axis: n })),
        btn("disable", "Disable", () => send("disable", { axis: n })),
        btn("home", "Home", () => send("home", { axis: n })),
        btn("stop", "Stop", () => send("stop", { axis: n })),
        el("span", {}, "at "), el("b", { testid: `axis-position-${n}` })),
      el("div", { class: "line" }, inp("move-to-input", "0mm"),
        btn("move-to", "Move to", () => send("move_to", { axis: n, position: val("move-to-input"), speed: val("speed") }))),
      el("div", { class: "line" }, inp("move-by-input", "1mm"),
        btn("move-by", "Move by", () => send("move_by", { axis: n, distance: val("move-by-input"), speed: val("speed") }))),
      el("div", { class: "line" }, el("span", {}, "speed"), inp("speed", "", 9),
        el("span", { class: "hint" }, "(empty: the axis's max)")),
      el("div", { class: "line" }, el("span", {}, "jog"), jogBtn(-1), jogBtn(1), el("span", {}, "at"),
        inp("jog-speed", "5mm/s", 8)),
      el("div", { class: "margins", testid: `margins-${n}` })));
  }
  const sel = $("#scope-axis");
  sel.replaceChildren(...names.map((n) => el("option", {}, n)));
  $("#explain-trace").replaceChildren();
}
function onStatus(st) {
  ui.status = st;
  const names = st.console.axis_names;
  if (!ui.built) {
    ui.axes = names;
    buildAxes(names);
    ui.built = true;
    buildScopeControls();
    subscribeScope();
  }
  $("#machine-line").textContent = `${st.bus} · ${st.clock} · t = ${fmt(st.console.time_s, 2)} s`;
  for (const n of names) {
    const a = st.axes[n];
    tid(`state-${n}`).textContent = a.state + (a.jog_held ? " (jog held)" : "");
    tid(`power-${n}`).textContent = a.power;
    tid(`axis-power-${n}`).textContent = `${a.state}, ${a.power}`;
    tid(`position-${n}`).textContent = fmt(a.position_m * 1e3, 4);
    tid(`axis-position-${n}`).textContent = `${fmt(a.position_m * 1e3, 4)} mm`;
    tid(`ferror-${n}`).textContent = fmt(a.following_error_m * 1e6, 2);
    tid(`effort-${n}`).textContent = `${fmt(a.effort, 3)} ${a.effort_unit}`;
    tid(`move-${n}`).textContent = a.move || "";
    const faulted = a.power === "Fault" || a.power === "Fault Reaction Active";
    const text = [faulted ? a.drive_error || "drive in Fault" : "", a.fault || "", a.read_error || ""]
      .filter((s) => s).join(" · ");
    tid(`fault-${n}`).textContent = text;
    tid(`fault-reset-${n}`).disabled = !faulted && !a.fault;
  }
  const body = $("#loop-health tbody");
  body.replaceChildren();
  for (const [k, v] of Object.entries(st)) {
    if (["axes", "console", "bus", "clock"].includes(k)) continue;
    let text = v;
    if (v !== null && typeof v === "object") text = Object.entries(v).map(([a, b]) => `${a}=${typeof b === "number" ? +b.toPrecision(4) : b}`).join(", ");
    else if (typeof v === "number") text = Number.isInteger(v) ? v : v.toPrecision(4);
    body.append(el("tr", {}, el("td", {}, k), el("td", { class: "num", testid: `loop-${k}` }, String(text))));
  }
  const cap = st.console.capture;
  if (cap && cap.state !== "done") $("#scope-state").textContent = `capture ${cap.state} on ${cap.axis}`;
}

// ---------------------------------------------------------------------------------------------- jog (dead man)
function jogStart(axis, dir, button) {
  jogStop("replaced");
  const speed = tid(`jog-speed-${axis}`).value;
  const deadman = (ui.status && ui.status.axes[axis].jog_deadman_s) || 0.2;
  const renew = Math.max(20, Math.min(100, deadman * 1000 / 4));  // several renewals per dead-man interval
  // each press has its number: the server ignores a renewal of a press that ended (one still in flight
  // when the release went out), so a release is final
  const press = (ui.presses = (ui.presses || 0) + 1);
  const j = { axis, dir, button, speed, press, stopped: false };
  const once = () => send("jog", { axis, direction: dir, speed, press }, (r) => { if (!r.ok) jogStop("refused"); });
  once();
  j.timer = setInterval(() => { if (!j.stopped) once(); }, renew);
  button.classList.add("held");
  ui.jog = j;
}
function jogStop(why) {
  const j = ui.jog;
  if (!j) return;
  ui.jog = null;
  j.stopped = true;
  clearInterval(j.timer);
  j.button.classList.remove("held");
  if (ui.ws && ui.ws.readyState === WebSocket.OPEN) send("jog_release", { axis: j.axis, why, press: j.press });
}
document.addEventListener("visibilitychange", () => { if (document.hidden) jogStop("hidden tab"); });
window.addEventListener("blur", () => jogStop("window lost focus"));
window.addEventListener("pagehide", () => jogStop("page closed"));

// ---------------------------------------------------------------------------------------------- scope
function buildScopeControls() {
  const box = $("#scope-channels");
  box.replaceChildren();
  for (const c of CHANNELS) {
    const cb = el("input", { type: "checkbox", testid: `scope-ch-${c}` });
    cb.checked = ["reference", "position", "following_error", "effort"].includes(c);
    box.append(el("label", {}, cb, c.replace("_", " ")));
  }
  $("#scope-level-channel").replaceChildren(...CHANNELS.map((c) => el("option", {}, c)));
  $("#scope-level-channel").value = "position";
}
function scopeChannels() { return CHANNELS.filter((c) => tid(`scope-ch-${c}`).checked); }
function parseSeconds(text) {
  const m = /^\s*([0-9.eE+-]+)\s*(s|ms)?\s*$/.exec(text);
  if (!m || !isFinite(+m[1])) return NaN;
  return +m[1] * (m[2] === "ms" ? 1e-3 : 1);
}
function subscribeScope() {
  const axis = $("#scope-axis").value || ui.axes[0];
  const w = parseSeconds($("#scope-window").value);
  if (!(w > 0)) { say(`scope: window ${JSON.stringify($("#scope-window").value)} is not a time (e.g. 5s)`, true); return; }
  ui.scope = { ...ui.scope, axis, channels: scopeChannels(), window: w, t: [], ch: {}, live: true, frozen: null };
  $("#scope-state").textContent = "live";
  send("scope", { axis, channels: ui.scope.channels, window_s: w });
}
$("#scope-apply").addEventListener("click", subscribeScope);
$("#scope-axis").addEventListener("change", subscribeScope);
function onScope(msg) {
  const s = ui.scope;
  if (msg.reset) { s.t = []; s.ch = {}; }
  s.t.push(...msg.t);
  for (const [c, v] of Object.entries(msg.channels)) { (s.ch[c] = s.ch[c] || []).push(...v); }
  const cut = s.t.length ? s.t[s.t.length - 1] - s.window : 0;
  let i = 0;
  while (i < s.t.length && s.t[i] < cut) i++;
  if (i) { s.t.splice(0, i); for (const c in s.ch) s.ch[c].splice(0, i); }
  s.samples = (s.samples || 0) + msg.t.length;
  if (s.live && scopeShown()) requestScopeDraw();  // drawn only where it is seen
}
// at most every 250 ms, and never more than a quarter of the page's time: a slow or loaded computer
// draws less often, it does not fall behind (the data keeps arriving whole)
const draw = { pending: false, last: 0, took: 0 };
function requestScopeDraw() {
  if (draw.pending) return;
  draw.pending = true;
  const wait = Math.max(0, Math.max(250, 4 * draw.took) - (performance.now() - draw.last));
  setTimeout(() => requestAnimationFrame(() => {
    draw.pending = false;
    if (!(ui.scope.live && scopeShown())) return;
    const t0 = performance.now();
    drawScope(ui.scope.t, ui.scope.ch, "t (s, loop time)");
    draw.last = performance.now();
    draw.took = draw.last - t0;
  }), wait);
}
const scopeShown = () => !$("#page-scope").classList.contains("hidden") && !document.hidden;
function onCapture(msg) {
  const s = ui.scope;
  s.live = false;
  s.frozen = msg;
  s.cursors = [];
  $("#scope-state").textContent = `frozen: capture on ${msg.axis}, trigger ${msg.trigger}${msg.detail ? " (" + msg.detail + ")" : ""}`;
  drawScope(msg.t, msg.channels, "t (s, from the trigger)");
  readout();
}
$("#scope-arm").addEventListener("click", () => {
  const trig = $("#scope-trigger").value;
  send("capture", { axis: $("#scope-axis").value, channels: scopeChannels(), trigger: trig,
    level_channel: $("#scope-level-channel").value, level: $("#scope-level").value,
    direction: $("#scope-direction").value, pre: $("#scope-pre").value, post: $("#scope-post").value });
});
$("#scope-freeze").addEventListener("click", () => {
  // freezing is a capture of the window just shown: the same path as a trigger, saved the same way
  send("capture", { axis: ui.scope.axis, channels: ui.scope.channels, trigger: "now",
    pre: `${Math.min(ui.scope.window, 4.9)}s`, post: "0s" });
});
$("#scope-live").addEventListener("click", () => { ui.scope.live = true; ui.scope.cursors = []; readout(); $("#scope-state").textContent = "live"; });
$("#scope-save").addEventListener("click", () => send("save", {}, (r) => { if (r.ok) loadTraceList(); }));
$("#scope-clear-cursors").addEventListener("click", () => { ui.scope.cursors = []; redrawFrozen(); readout(); });

// min/max per pixel column: every column keeps its lowest and highest sample, in time order (no peak lost)
function decimate(t, y, t0, t1, columns) {
  const n = t.length;
  if (n <= 2 * columns) return { x: t.slice(), y: y.slice() };
  const x = [], out = [];
  const width = (t1 - t0) / columns || 1;
  let col = -1, iMin = -1, iMax = -1;
  const flush = () => {
    if (iMin < 0) return;
    const a = Math.min(iMin, iMax), b = Math.max(iMin, iMax);
    x.push(t[a]); out.push(y[a]);
    if (b !== a) { x.push(t[b]); out.push(y[b]); }
  };
  for (let i = 0; i < n; i++) {
    if (t[i] < t0 || t[i] > t1) continue;
    const c = Math.floor((t[i] - t0) / width);
    if (c !== col) { flush(); col = c; iMin = iMax = i; continue; }
    if (y[i] < y[iMin]) iMin = i;
    if (y[i] > y[iMax]) iMax = i;
  }
  flush();
  return { x, y: out };
}
window.__drivectl.decimate = decimate;
window.__drivectl.setCursor = (x) => setCursor(x);

function axesLayout(groups, xtitle) {
  const layout = { margin: { l: 60, r: 20 + 60 * Math.max(0, groups.length - 1), t: 10, b: 40 }, showlegend: true,
    legend: { orientation: "h", y: 1.08 }, xaxis: { title: { text: xtitle }, domain: [0, 1 - 0.07 * Math.max(0, groups.length - 2)] },
    uirevision: "keep", shapes: [] };
  groups.forEach((g, i) => {
    const key = i === 0 ? "yaxis" : `yaxis${i + 1}`;
    layout[key] = { title: { text: g.title }, zeroline: false };
    if (i > 0) Object.assign(layout[key], { overlaying: "y", side: "right", anchor: i === 1 ? "x" : "free",
      position: i === 1 ? undefined : 1 - 0.07 * (groups.length - 1 - i) });
  });
  return layout;
}
// "position [mm]", "effort [N]" (the axis's effort unit), "statusword"
function label(c, effortUnit) {
  const [g, , unit] = UNIT[c] || ["eff", 1, ""];
  const u = unit || (g === "eff" ? effortUnit : "");
  return `${c}${u ? " [" + u + "]" : ""}`;
}
function effortUnitShown() {
  if (!ui.scope.live && ui.scope.frozen) return ui.scope.frozen.effort_unit || "";
  return ui.status ? ui.status.axes[ui.scope.axis || ui.axes[0]].effort_unit : "";
}
function chartTraces(t, channels, div, effortUnit) {
  const names = Object.keys(channels);
  const groups = [];
  const data = [];
  const width = Math.max(100, (div.clientWidth || 800) - 120);
  const t0 = t.length ? t[0] : 0, t1 = t.length ? t[t.length - 1] : 1;
  for (const c of names) {
    const [g, scale, unit] = UNIT[c] || ["eff", 1, ""];
    let gi = groups.findIndex((x) => x.key === g);
    if (gi < 0) { groups.push({ key: g, title: unit || (g === "eff" ? effortUnit || "effort" : g) }); gi = groups.length - 1; }
    const y = channels[c].map((v) => (v === null ? NaN : v * scale));
    const d = decimate(t, y, t0, t1, width);
    data.push({ x: d.x, y: d.y, name: label(c, effortUnit), mode: "lines", line: { width: 1.3 },
      yaxis: gi === 0 ? "y" : `y${gi + 1}` });
  }
  return { data, groups };
}
function drawScope(t, channels, xtitle) {
  const div = $("#scope");
  const { data, groups } = chartTraces(t, channels, div, effortUnitShown());
  const layout = axesLayout(groups, xtitle);
  layout.shapes = ui.scope.cursors.map((x, i) => ({ type: "line", x0: x, x1: x, yref: "paper", y0: 0, y1: 1,
    line: { color: i ? "#d62" : "#26d", dash: "dot" } }));
  Plotly.react(div, data, layout, { displaylogo: false, responsive: true });
}
function redrawFrozen() { const f = ui.scope.frozen; if (f && !ui.scope.live) drawScope(f.t, f.channels, "t (s, from the trigger)"); }
function nearest(t, x) {
  let lo = 0, hi = t.length - 1;
  while (hi - lo > 1) { const mid = (lo + hi) >> 1; if (t[mid] < x) lo = mid; else hi = mid; }
  return Math.abs(t[lo] - x) <= Math.abs(t[hi] - x) ? lo : hi;
}
function readout() {
  const body = $("#scope-readout tbody");
  body.replaceChildren();
  const s = ui.scope;
  const src = s.live ? { t: s.t, channels: s.ch } : s.frozen;
  if (!src || !s.cursors.length || !src.t.length) return;
  const idx = s.cursors.map((x) => nearest(src.t, x));
  body.append(el("tr", {}, el("th", {}, "channel"), ...idx.map((i, k) => el("th", {}, `${"AB"[k]} @ ${src.t[i].toFixed(4)} s`)),
    ...(idx.length === 2 ? [el("th", {}, `B − A (Δt ${(src.t[idx[1]] - src.t[idx[0]]).toFixed(4)} s)`)] : [])));
  for (const [c, v] of Object.entries(src.channels)) {
    const [, scale] = UNIT[c] || ["", 1, ""];
    const vals = idx.map((i) => v[i] * scale);
    body.append(el("tr", {}, el("td", {}, label(c, effortUnitShown())),
      ...vals.map((x) => el("td", { class: "num" }, x.toPrecision(7))),
      ...(vals.length === 2 ? [el("td", { class: "num" }, (vals[1] - vals[0]).toPrecision(5))] : [])));
  }
}
function chartClick(div, onX) {
  div.on("plotly_click", (ev) => { if (ev.points && ev.points.length) onX(ev.points[0].x); });
}
function setCursor(x) {
  const s = ui.scope;
  if (s.live) { say("cursors: freeze the scope first (Freeze, or a trigger)"); return; }
  s.cursors = s.cursors.length >= 2 ? [x] : [...s.cursors, x];
  redrawFrozen();
  readout();
}

// ---------------------------------------------------------------------------------------------- traces
async function api(path, opts) {
  const r = await fetch(withToken(path), opts);
  const body = await r.json();
  if (!r.ok || body.error) throw new Error(body.error || r.statusText);
  return body;
}
async function loadTraceList() {
  let list;
  try { list = await api("/api/traces"); } catch (e) { say(`traces: ${e.message}`, true); return; }
  const body = $("#traces-table tbody");
  body.replaceChildren(el("tr", {}, el("th", {}, "trace"), el("th", {}, "kB")));
  for (const e of list) {
    const row = el("tr", { testid: `trace-row-${e.name}` }, el("td", {}, e.name), el("td", { class: "num" }, (e.bytes / 1024).toFixed(1)));
    row.addEventListener("click", () => { for (const r of body.children) r.classList.remove("sel"); row.classList.add("sel"); showTrace(e.name); });
    body.append(row);
  }
  const sel = $("#explain-trace");
  const keep = sel.value;
  sel.replaceChildren(...list.map((e) => el("option", {}, e.name)));
  if (keep) sel.value = keep;
}
$("#traces-refresh").addEventListener("click", loadTraceList);

// the last `drivectl bode --loop open --out <this console's folder>` of each axis, on its Axis card
async function loadMargins() {
  let got;
  try { got = await api("/api/margins"); } catch (e) { say(`margins: ${e.message}`, true); return; }
  for (const n of ui.axes) {
    const box = tid(`margins-${n}`);
    if (!box) continue;
    const f = got[n];
    if (!f) {
      box.replaceChildren(el("span", { class: "hint" },
        `margins: run drivectl bode --axis ${n} --loop open --out <this console's folder> to see them here`));
      continue;
    }
    const m = f.margins || {};
    const v = (x, d, u) => (x === null || x === undefined ? "–" : `${Number(x).toFixed(d)}${u}`);
    const kind = m.linear === false ? " (describing-function estimate: a nonlinear law)" : "";
    box.replaceChildren(
      el("div", { class: "line", testid: `margins-line-${n}` },
        `margins (${m.controller || "?"}${kind}, ${new Date(f.mtime * 1000).toLocaleString()}): ` +
        `GM ${v(m.gm_db, 2, " dB")} at ${v(m.gm_hz, 1, " Hz")}, PM ${v(m.pm_deg, 1, "°")} at ${v(m.pm_hz, 1, " Hz")}, ` +
        `Ms ${v(m.ms, 2, "")}, bandwidth ${v(m.bandwidth_hz, 1, " Hz")}`),
      el("img", { testid: `margins-png-${n}`, alt: `open loop of axis ${n}`, style: "max-width: 100%",
        src: withToken(`/files/${encodeURIComponent(f.png)}?v=${f.mtime}`) }));
  }
}
async function showTrace(name) {
  let tr;
  try { tr = await api(`/api/trace?name=${encodeURIComponent(name)}`); } catch (e) { say(`trace ${name}: ${e.message}`, true); return; }
  ui.trace = tr;
  $("#trace-title").textContent = `${name} (${tr.rows} rows)`;
  const t = tr.columns.time_s;
  const channels = {};
  for (const [col, ch] of Object.entries(COLUMN_CHANNEL)) if (tr.columns[col]) channels[ch] = tr.columns[col];
  if (tr.columns.ref_m && tr.columns.pos_m && !tr.columns.following_error_m) {
    channels.following_error = tr.columns.ref_m.map((r, i) => r - tr.columns.pos_m[i]);
  }
  ui.trace.channels = channels;
  drawTrace(t[0], t[t.length - 1]);
  const div = $("#trace-plot");
  div.removeAllListeners && div.removeAllListeners("plotly_relayout");
  div.on("plotly_relayout", (ev) => {  // zoom: decimate again for the range shown (full resolution when close)
    const range = ev["xaxis.range"] || (ev["xaxis.range[0]"] !== undefined && [ev["xaxis.range[0]"], ev["xaxis.range[1]"]]);
    if (range) drawTrace(+range[0], +range[1], true);
    else if (ev["xaxis.autorange"]) drawTrace(t[0], t[t.length - 1]);
  });
  const body = $("#trace-summary tbody");
  body.replaceChildren(...Object.entries(tr.summary).map(([k, v]) =>
    el("tr", {}, el("td", {}, k), el("td", { class: "num" }, typeof v === "number" ? v.toPrecision(5) : String(v)))));
  for (const [k, v] of Object.entries(tr.meta)) body.append(el("tr", {}, el("td", {}, k), el("td", {}, v)));
}
function drawTrace(t0, t1, zoomed = false) {
  const tr = ui.trace, div = $("#trace-plot");
  const t = tr.columns.time_s;
  const i0 = Math.max(0, nearest(t, t0) - 1), i1 = Math.min(t.length, nearest(t, t1) + 2);
  const sub = {};
  for (const [c, v] of Object.entries(tr.channels)) sub[c] = v.slice(i0, i1);
  const { data, groups } = chartTraces(t.slice(i0, i1), sub, div, tr.meta.effort_unit);
  const layout = axesLayout(groups, "t (s)");
  if (zoomed) layout.xaxis.range = [t0, t1];
  layout.uirevision = zoomed ? "zoom" : tr.name;
  Plotly.react(div, data, layout, { displaylogo: false, responsive: true });
}

// ---------------------------------------------------------------------------------------------- explain
$("#explain-run").addEventListener("click", async () => {
  const name = $("#explain-trace").value;
  if (!name) { say("explain: no trace chosen (the folder has none yet?)", true); return; }
  $("#explain-state").textContent = "running…";
  $("#explain-report").textContent = "";
  $("#explain-png").removeAttribute("src");
  try {
    const r = await api("/api/explain", { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ name, plant: $("#explain-plant").value }) });
    $("#explain-report").textContent = r.report;
    if (r.png) $("#explain-png").src = withToken(`/files/${r.png}`);
    $("#explain-state").textContent = `done (plant ${r.plant})`;
  } catch (e) {
    $("#explain-state").textContent = "failed";
    say(`explain: ${e.message}`, true);
  }
});

// ---------------------------------------------------------------------------------------------- start
Plotly.newPlot("scope", [], axesLayout([], "t (s)"), { displaylogo: false, responsive: true });
chartClick($("#scope"), setCursor);
connect();
