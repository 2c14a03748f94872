// drivectl console: the Health page (docs/health.md): the store's fleet table, one axis's trend panels
// (one per effect: the parameter over time, its band, the onset of an alarm, the limit), the fingerprint run.
"use strict";

ui.health = { fleet: null, axis: null, last: null, running: false };

const healthNum = (v) => (v === null || v === undefined ? "–" : Number(v).toPrecision(4));

async function loadHealthFleet() {
  let got;
  try { got = await api("/api/health"); } catch (e) { say(`health: ${e.message}`, true); return; }
  ui.health.fleet = got;
  $("#health-store").textContent = `store ${got.store}` + (got.note ? ` (${got.note})` : "");
  if (!$("#health-machine").value) $("#health-machine").value = got.machine || "";
  const body = $("#health-fleet tbody");
  body.replaceChildren(el("tr", {}, ...["machine", "axis", "runs", "analysed", "worst alarm"].map((h) => el("th", {}, h))));
  for (const r of got.axes) {
    const w = r.worst;
    let what = "none";
    if (w) {
      const lim = w.limit === null ? "no limit" : w.runs_to_limit === null ? `limit ${healthNum(w.limit)}: not towards it`
        : w.runs_to_limit === 0 ? `past its limit ${healthNum(w.limit)}` : `limit ${healthNum(w.limit)} in ${Math.round(w.runs_to_limit)} runs`;
      what = `${w.key} from run ${w.onset_run}: ${healthNum(w.first_value)} → ${healthNum(w.last_value)}; ${lim}`;
    }
    const row = el("tr", { testid: `health-row-${r.machine}-${r.axis}`, class: w ? "alarm" : "" },
      el("td", {}, r.machine), el("td", {}, r.axis), el("td", { class: "num" }, String(r.runs)),
      el("td", { class: "num" }, String(r.fitted)), el("td", {}, what));
    row.addEventListener("click", () => {
      for (const x of body.children) x.classList.remove("sel");
      row.classList.add("sel");
      loadHealthAxis(r.machine, r.axis);
    });
    body.append(row);
  }
  if (ui.health.axis) loadHealthAxis(ui.health.axis.machine, ui.health.axis.axis);
}

async function loadHealthAxis(machine, axis) {
  let got;
  try { got = await api(`/api/health/axis?machine=${encodeURIComponent(machine)}&axis=${encodeURIComponent(axis)}`); }
  catch (e) { say(`health ${machine}/${axis}: ${e.message}`, true); return; }
  ui.health.axis = { machine, axis, ...got };
  const rep = got.report;
  $("#health-title").textContent = `${machine}/${axis}: ${rep.runs} runs, ${rep.alarms.length} alarm${rep.alarms.length === 1 ? "" : "s"}`;
  const body = $("#health-alarms tbody");
  body.replaceChildren();
  if (rep.alarms.length) {
    body.append(el("tr", {}, ...["alarm", "onset run", "onset (UTC)", "then", "now", "per 100 runs"].map((h) => el("th", {}, h))));
    for (const a of rep.alarms) {
      body.append(el("tr", { testid: `health-alarm-${a.effect}-${a.param}` }, el("td", {}, `${a.effect}.${a.param}`),
        el("td", { class: "num" }, String(a.onset_run)), el("td", {}, a.onset_utc), el("td", { class: "num" }, healthNum(a.first_value)),
        el("td", { class: "num" }, healthNum(a.last_value)), el("td", { class: "num" }, healthNum(a.slope_per_100_runs))));
    }
  }
  const panels = $("#health-panels");
  panels.replaceChildren();
  for (const [effect, series] of Object.entries(got.panels)) {
    const div = el("div", { class: "panel", testid: `health-panel-${effect}` });
    panels.append(div);
    const data = [], shapes = [];
    const alarm = series.some((s) => s.alarm);
    series.slice(0, 2).forEach((s, j) => {
      const yaxis = j === 0 ? "y" : "y2";
      const x = [], y = [], lo = [], hi = [];
      s.values.forEach((v, i) => {
        if (v === null) return;
        const band = s.uncertainties[i] !== null ? s.uncertainties[i] : (s.sigma || 0);
        x.push(s.times[i]); y.push(v); lo.push(v - band); hi.push(v + band);
      });
      const color = j === 0 ? "#1f77b4" : "#ff7f0e";
      data.push({ x: x.concat([...x].reverse()), y: hi.concat([...lo].reverse()), fill: "toself", line: { width: 0 },
        fillcolor: j === 0 ? "rgba(31,119,180,0.18)" : "rgba(255,127,14,0.18)", hoverinfo: "skip", showlegend: false, yaxis });
      data.push({ x, y, mode: "lines+markers", name: s.param, line: { color, width: 1 }, marker: { size: 4 }, yaxis });
      if (s.limit !== null) shapes.push({ type: "line", xref: "paper", x0: 0, x1: 1, yref: yaxis, y0: s.limit, y1: s.limit, line: { color, dash: "dash", width: 1 } });
      if (s.onset_utc) shapes.push({ type: "line", yref: "paper", y0: 0, y1: 1, x0: s.onset_utc, x1: s.onset_utc, line: { color: s.alarm ? "red" : "grey", width: s.alarm ? 2 : 1, dash: s.alarm ? "solid" : "dot" } });
    });
    const layout = { title: { text: effect + (alarm ? "  ALARM" : ""), x: 0.01, xanchor: "left", font: { size: 12, color: alarm ? "red" : "black" } },
      margin: { l: 50, r: 50, t: 28, b: 30 }, height: 220, shapes, showlegend: true, legend: { orientation: "h", y: -0.25 },
      yaxis: { title: { text: series[0].param, font: { size: 10 } } } };
    if (series.length > 1) layout.yaxis2 = { overlaying: "y", side: "right", title: { text: series[1].param, font: { size: 10 } } };
    Plotly.newPlot(div, data, layout, { displaylogo: false, responsive: true });
  }
}

function healthStatus(st) {
  const h = st.console && st.console.health;
  if (!h) return;
  const sel = $("#health-axis");
  if (sel.options.length !== (st.console.axis_names || []).length) {
    sel.replaceChildren(...st.console.axis_names.map((n) => el("option", {}, n)));
  }
  const was = ui.health.running;
  ui.health.running = h.running;
  ui.health.last = h.last;
  $("#health-state").textContent = h.last ? h.last.line : "";
  $("#health-run").disabled = h.running;
  if (was && !h.running && !$("#page-health").classList.contains("hidden")) loadHealthFleet();
}

const baseOnStatus = onStatus;
onStatus = function (st) { baseOnStatus(st); healthStatus(st); };  // eslint-disable-line no-func-assign
const baseShowPage = showPage;
showPage = function (name) { baseShowPage(name); if (name === "health") loadHealthFleet(); };  // eslint-disable-line no-func-assign

$("#health-run").addEventListener("click", () => {
  send("health_run", { axis: $("#health-axis").value, machine: $("#health-machine").value });
});
$("#health-refresh").addEventListener("click", loadHealthFleet);
$("#health-analyze").addEventListener("click", async () => {
  $("#health-state").textContent = "analysing…";
  try {
    const r = await api("/api/health/analyze", { method: "POST" });
    $("#health-state").textContent = r.line;
    if (!r.ok) say(r.errors.length ? r.errors[r.errors.length - 1] : r.line, true);
  } catch (e) { say(`health analyze: ${e.message}`, true); $("#health-state").textContent = "failed"; }
  loadHealthFleet();
});
