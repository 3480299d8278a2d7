// msk-live coaches' dashboard: one WebSocket, newest frame per topic, redrawn at most once per animation frame.
"use strict";

const TORQUE_WINDOW_S = 10;
const RECONNECT_MIN_MS = 500, RECONNECT_MAX_MS = 3000;

const state = {
  config: null, socket: null, lastMessageMs: 0, reconnectMs: RECONNECT_MIN_MS, connection: "connecting",
  activations: {}, joints: null, load: null, session: null, reps: null, devices: {}, nodes: {}, envelopes: null,
  electrodes: [], // each EMG electrode's signal quality (the estimator's status)
  dataAge: null, activationAge: null,
  method: localStorage.getItem("msk-method") || null, pack: null, packGroupsKey: null, updates: 0,
  torqueHistory: {}, // method -> coordinate -> {t: [], id: [], model: []}
};
const charts = { bars: null, torques: {} };
window.mskDashboard = { state, charts, merge: (update) => { merge(update); scheduleRender(); } };
// Read from the rack: chart text at 18 px at least, in the foreground colour (the page's CSS does the same for text).
const MIN_TEXT_PX = 18;
if (window.Chart) { Chart.defaults.font.size = MIN_TEXT_PX; Chart.defaults.color = "#1d2630"; }

// Same colour scale as services/surfaces/dashboard/bodymap.py COLOUR_STOPS: yellow (0) -> orange (25 %) -> red -> dark red (1),
// so that low activations stand out from the grey body.
const STOPS = [[0, [255, 222, 60]], [0.25, [253, 160, 40]], [0.5, [234, 85, 35]], [0.75, [180, 20, 30]], [1, [100, 0, 20]]];
// Traces: the last TRACE_WINDOW_S of the chosen muscles (estimate with its band, measured envelope where an electrode is).
const TRACE_WINDOW_S = 10, TRACE_DEFAULT_COUNT = 3;
const TRACE_COLOURS = ["#1f5fbf", "#d9480f", "#2b8a3e", "#862e9c", "#c2255c", "#495057"];
state.traces = {}; // method -> group -> {t: [], a: [], lo: [], hi: [], e: []}
state.traceGroups = null; // the muscles traced (null: the default, those with an electrode)
state.fatigue = []; // each EMG electrode's fatigue index over the set (the estimator's status)
// The traces' other mode: the set's last REP_OVERLAY_COUNT reps overlaid on normalised rep time (the phase, 0-100 %).
const REP_OVERLAY_COUNT = 6;
state.traceMode = "time"; // "time": the last 10 s; "reps": the reps overlaid
state.repOverlay = {}; // method -> {set, lastPhase, reps: [{group: [{x: phase %, y: activation %}]}]}
function activationColour(v) {
  if (v === null || v === undefined || Number.isNaN(v)) return "#b8bec7";
  v = Math.min(Math.max(v, 0), 1);
  for (let i = 1; i < STOPS.length; i++) {
    const [v0, c0] = STOPS[i - 1], [v1, c1] = STOPS[i];
    if (v <= v1) {
      const f = (v - v0) / (v1 - v0);
      const c = c0.map((a, k) => Math.round(a + (c1[k] - a) * f));
      return "#" + c.map((x) => x.toString(16).padStart(2, "0")).join("");
    }
  }
  return "#640014";
}

function connect() {
  const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
  const socket = new WebSocket(url);
  state.socket = socket;
  socket.onopen = () => { state.reconnectMs = RECONNECT_MIN_MS; state.lastMessageMs = Date.now(); };
  socket.onmessage = (event) => {
    state.lastMessageMs = Date.now();
    state.connection = "open";
    merge(JSON.parse(event.data));
    scheduleRender();
  };
  socket.onclose = (event) => {
    if (state.socket !== socket) return;
    state.socket = null;
    // 1008 after the socket opened: the operator revoked this tablet's token (access.py); retrying cannot help
    if (event.code === 1008) { withdrawn(); return; }
    state.connection = "reconnecting";
    scheduleRender();
    setTimeout(start, state.reconnectMs);
    state.reconnectMs = Math.min(state.reconnectMs * 2, RECONNECT_MAX_MS);
  };
}

// A bridge that stops answering without closing the socket (machine asleep, network cut) counts as gone.
setInterval(() => {
  const limit = 4000 * (state.config ? state.config.heartbeat_s : 0.5);
  if (state.socket && state.connection === "open" && Date.now() - state.lastMessageMs > limit) {
    state.socket.close();
  }
  scheduleRender();
}, 500);

// The tablet's token was revoked (msk certs revoke-token): say so and stop reconnecting; only a new link helps.
function withdrawn() {
  state.connection = "withdrawn";
  scheduleRender();
}

function merge(update) {
  state.updates += 1;
  state.dataAge = update.data_age_s;
  state.activationAge = update.activation_age_s;
  if (update.devices) state.devices = update.devices;
  if (update.nodes) state.nodes = update.nodes;
  for (const [topic, value] of Object.entries(update.topics || {})) {
    if (topic.startsWith("activations/")) {
      const method = topic.slice("activations/".length);
      state.activations[method] = value;
      recordTorques(method, value);
      recordTraces(method, value);
      recordRepOverlay(method, value);
    } else if (topic === "joints") state.joints = value;
    else if (topic === "load") state.load = value;
    else if (topic === "session") state.session = value;
    else if (topic === "reps") state.reps = value;
    else if (topic === "sets") state.sets = value; // every set: msk_core.signal.sets.SetRecord.as_dict
    else if (topic === "envelopes") state.envelopes = value;
    else if (topic === "electrodes") state.electrodes = value;
    else if (topic === "fatigue") state.fatigue = value;
  }
}

// Display names (the session entry: the pack's, or the session file's [names]); the model name where none is known.
function groupName(group) {
  const names = state.session && state.session.names;
  return (names && names.groups[group]) || group;
}
function coordinateName(coordinate) {
  const names = state.session && state.session.names;
  const entry = names && names.coordinates[coordinate];
  return { name: entry ? entry.name : coordinate, torqueUnit: entry && entry.torque_unit ? entry.torque_unit : "N·m" };
}
// A bar label: the display name, on two lines at its comma where there is room for them (Chart.js takes an array).
function barLabel(group, count) {
  const name = groupName(group);
  const comma = name.indexOf(", ");
  return count <= 20 && comma > 0 ? [name.slice(0, comma + 1), name.slice(comma + 2)] : name;
}

function recordTorques(method, frame) {
  const byCoordinate = (state.torqueHistory[method] = state.torqueHistory[method] || {});
  for (const t of frame.torques) {
    let h = byCoordinate[t.coordinate];
    if (!h || (h.t.length && frame.time_s < h.t[h.t.length - 1])) h = byCoordinate[t.coordinate] = { t: [], id: [], model: [] };
    h.t.push(frame.time_s); h.id.push(t.inverse_dynamics_nm); h.model.push(t.model_nm);
    while (h.t.length && h.t[0] < frame.time_s - TORQUE_WINDOW_S) { h.t.shift(); h.id.shift(); h.model.shift(); }
  }
}

let renderPending = false;
function scheduleRender() {
  if (!renderPending) { renderPending = true; requestAnimationFrame(() => { renderPending = false; render(); }); }
}

function currentMethod() {
  const methods = Object.keys(state.activations).sort();
  if (!methods.length) return null;
  if (!state.method || !methods.includes(state.method)) {
    const preferred = (state.config && state.config.default_methods) || [];  // as view and report: assisted where EMG is live
    state.method = preferred.find((m) => methods.includes(m)) || methods[0];
  }
  return state.method;
}

function render() {
  const noDataAfter = state.config ? state.config.no_data_after_s : 2;
  // Live = activation frames arrive: devices that still deliver without estimates are no data for a coach.
  const age = state.activationAge;
  const live = state.connection === "open" && age !== null && age !== undefined && age <= noDataAfter;
  const status = document.getElementById("status");
  const pill = state.connection !== "open" ? state.connection : (live ? "live" : "nodata");
  status.className = "pill pill-" + pill;
  status.dataset.state = pill;
  document.body.dataset.state = pill; // greys the last values out (dashboard.css) while not live
  const delivering = state.dataAge !== null && state.dataAge !== undefined && state.dataAge <= noDataAfter;
  const paused = !live && state.connection === "open" && state.session && state.session.paused && delivering;
  status.textContent = paused ? "paused"
    : { live: "live", nodata: "no data", connecting: "connecting", reconnecting: "reconnecting",
      withdrawn: "access withdrawn" }[pill];
  const overlay = document.getElementById("nodata");
  overlay.hidden = pill === "live";
  const session = state.config ? state.config.session : "?";
  document.querySelector(".nodata-title").textContent = paused ? "Estimates paused"
    : pill === "withdrawn" ? "Access withdrawn" : "No data";
  document.getElementById("nodata-detail").textContent = pill === "withdrawn"
    ? "This tablet's access to the dashboard was withdrawn by the operator: ask the operator for a new link."
    : state.connection !== "open"
    ? "The dashboard server is not answering; reconnecting by itself."
    : state.dataAge === null || state.dataAge === undefined
      ? `Nothing received yet on msk/${session}/…: are the estimator and the devices running for session "${session}"?`
      : paused
        ? state.session.paused
      : age === null || age === undefined || (state.dataAge <= noDataAfter && age > noDataAfter)
        ? `The devices deliver but no muscle estimates arrive on msk/${session}/activations/…: is the estimator running?`
        : `Nothing received from session "${session}" for ${age.toFixed(0)} s: it has ended or stopped sending. `
          + "The last values are shown greyed out.";
  renderHeader();
  renderMethods();
  const method = currentMethod();
  const frame = method ? state.activations[method] : null;
  if (frame) { renderBars(frame); renderBodyMap(frame); renderTorques(method); }
  renderDevices(frame);
  renderNodes();
  renderElectrodes(frame);
  if (frame) renderTraces(method, frame);
  renderFatigue(frame);
}

// Exercise, load and athlete from the operator's load event (the exercise falls back to the activation frames').
function renderHeader() {
  const facts = state.session;
  if (facts) {
    document.getElementById("exercise").textContent = facts.exercise ? facts.exercise.replaceAll("_", " ") : "–";
    document.getElementById("load").textContent = facts.load_kg === null ? "–" : `${facts.load_kg.toFixed(1)} kg`;
    const athlete = document.getElementById("athlete");
    athlete.textContent = facts.athlete || "";
    athlete.title = facts.athlete ? `athlete ${facts.athlete}` : "";
    document.title = `${facts.athlete ? `${facts.athlete} · ` : ""}${state.config ? state.config.session : ""} · msk-live`;
  }
  const reps = state.reps;
  // set N and rep n of the set (the rep under way, else the last done); "N done" while resting after it
  document.getElementById("reps").textContent = reps && reps.set ? (reps.rep ?? reps.in_set) : "–"; // no set yet: "–"
  document.getElementById("set").textContent = reps && reps.set ? (reps.resting ? `${reps.set} done` : reps.set) : "–";
  document.getElementById("set-time").textContent = reps && !reps.resting && reps.time_in_set_s != null
    ? `· ${Math.max(0, reps.time_in_set_s).toFixed(0)} s` : (reps && reps.resting && reps.set ? "· resting" : "");
  renderSets();
  const phase = reps ? reps.phase : null;
  const fill = document.getElementById("phase-fill");
  const text = document.getElementById("phase-text");
  if (phase === null || phase === undefined) { fill.style.width = "0"; text.textContent = "unknown"; }
  else if (phase < 0) { fill.style.width = "0"; text.textContent = "rest"; }
  else {
    fill.style.width = `${(100 * phase).toFixed(0)}%`;
    text.textContent = reps.movement ?? "in a rep";  // from the joint power: right for any exercise
  }
}

function renderMethods() {
  const select = document.getElementById("method");
  const methods = Object.keys(state.activations).sort();
  if (select.options.length !== methods.length || methods.some((m, i) => select.options[i].value !== m)) {
    select.replaceChildren(...methods.map((m) => new Option(m, m)));
  }
  const method = currentMethod();
  if (method && select.value !== method) select.value = method;
}
document.getElementById("method").addEventListener("change", (event) => {
  state.method = event.target.value;
  localStorage.setItem("msk-method", state.method);
  scheduleRender();
});

function renderBars(frame) {
  const labels = frame.groups.map((g) => barLabel(g, frame.groups.length));
  const a = frame.activations.map((v) => (v === null ? 0 : v));
  const uncertainty = frame.std.length === labels.length
    ? frame.std.map((s, i) => (s === null ? null : [Math.max(0, a[i] - s), Math.min(1, a[i] + s)])) : labels.map(() => null);
  const envelope = frame.envelope && frame.envelope.length === labels.length
    ? frame.envelope.map((e) => (e === null ? null : [Math.max(0, e - 0.008), Math.min(1.02, e + 0.008)])) : labels.map(() => null);
  if (!charts.bars) {
    charts.bars = new Chart(document.getElementById("bars"), {
      type: "bar",
      data: { labels, datasets: [
        { label: "estimate", data: a, backgroundColor: a.map(activationColour), borderColor: "#5b6470", borderWidth: 1, grouped: false, barPercentage: 0.85, order: 3 },
        { label: "± uncertainty", data: uncertainty, backgroundColor: "rgba(29,38,48,.35)", grouped: false, barPercentage: 0.14, order: 2 },
        { label: "measured envelope", data: envelope, backgroundColor: "#1f5fbf", grouped: false, barPercentage: 1.0, order: 1 },
      ] },
      options: {
        indexAxis: "y", animation: false, responsive: true, maintainAspectRatio: false,
        scales: {
          // grid every 25 %, labelled every 50 %: 18 px labels side by side, not turned
          x: { min: 0, max: 1, ticks: { stepSize: 0.25, maxRotation: 0, autoSkip: false, font: { size: 18 }, color: "#1d2630", callback: (v) => (Math.round(v * 100) % 50 === 0 ? `${Math.round(v * 100)}%` : "") } },
          y: { ticks: { autoSkip: false, font: { size: 18 }, color: "#1d2630" } }, // every muscle named
        },
        plugins: { legend: { display: false }, tooltip: { enabled: true } },
      },
    });
    return;
  }
  const chart = charts.bars;
  chart.data.labels = labels;
  chart.data.datasets[0].data = a;
  chart.data.datasets[0].backgroundColor = a.map(activationColour);
  chart.data.datasets[1].data = uncertainty;
  chart.data.datasets[2].data = envelope;
  chart.update("none");
}

function packFor(groups) {
  if (!state.config) return null;
  const key = groups.join(",");
  for (const [name, packGroups] of Object.entries(state.config.packs)) if (packGroups.join(",") === key) return name;
  return null;
}

// The body map's own text ("front", "back") is drawn at the map's scale: set it so it shows at MIN_TEXT_PX on screen.
function readableMapText() {
  for (const text of document.querySelectorAll("#bodymap svg text")) {
    const scale = text.getScreenCTM() ? text.getScreenCTM().a : 1;
    if (scale > 0) text.setAttribute("font-size", (MIN_TEXT_PX / scale).toFixed(1));
  }
}
window.addEventListener("resize", readableMapText);

function renderBodyMap(frame) {
  const key = frame.groups.join(",");
  const box = document.getElementById("bodymap");
  if (state.packGroupsKey !== key) {
    state.packGroupsKey = key;
    state.pack = packFor(frame.groups);
    box.replaceChildren();
    if (!state.pack) { box.textContent = "These muscle groups match no shipped model pack: no body map."; return; }
    const pack = state.pack;
    fetch(`/bodymap/${pack}.svg`).then((r) => r.text()).then((svg) => {
      if (state.pack !== pack) return;
      box.innerHTML = svg;
      readableMapText();
      const mapped = new Set([...box.querySelectorAll(".muscle")].map((e) => e.dataset.group));
      const missing = frame.groups.filter((g) => !mapped.has(g));
      document.getElementById("unmapped").textContent = missing.length ? `not on the map: ${missing.map(groupName).join(", ")}` : "";
      scheduleRender();
    });
  }
  const value = Object.fromEntries(frame.groups.map((g, i) => [g, frame.activations[i]]));
  for (const shape of box.querySelectorAll(".muscle")) {
    const colour = activationColour(value[shape.dataset.group]);
    if (shape.getAttribute("fill") !== colour) shape.setAttribute("fill", colour);
  }
}

function renderTorques(method) {
  const history = state.torqueHistory[method] || {};
  const box = document.getElementById("torques");
  for (const [coordinate, h] of Object.entries(history)) {
    let chart = charts.torques[coordinate];
    if (!chart) {
      const wrap = document.createElement("div");
      wrap.innerHTML = `<div class="torque-title"></div><div class="torque"><canvas></canvas></div>`;
      box.appendChild(wrap);
      chart = charts.torques[coordinate] = new Chart(wrap.querySelector("canvas"), {
        type: "line",
        data: { datasets: [
          { label: "inverse dynamics", data: [], borderColor: "#1d2630", borderWidth: 2, pointRadius: 0 },
          { label: "model", data: [], borderColor: "#e63c28", borderWidth: 2, borderDash: [5, 3], pointRadius: 0 },
        ] },
        options: {
          animation: false, responsive: true, maintainAspectRatio: false, parsing: false, normalized: true,
          scales: { x: { type: "linear", min: -TORQUE_WINDOW_S, max: 0, ticks: { maxTicksLimit: 6, callback: (v) => `${v.toFixed(0)} s` } }, y: { ticks: { maxTicksLimit: 4 } } },
          plugins: { legend: { display: Object.keys(charts.torques).length === 0, position: "top", labels: { boxWidth: 18, font: { size: 18 }, color: "#1d2630" } } },
        },
      });
      chart.wrap = wrap;
    }
    const { name, torqueUnit } = coordinateName(coordinate); // names may come after the chart was made
    const title = `${name} (${torqueUnit})`;
    const titleBox = chart.wrap.querySelector(".torque-title");
    if (titleBox.textContent !== title) titleBox.textContent = title;
    const latest = h.t.length ? h.t[h.t.length - 1] : 0; // x: seconds before the newest frame
    chart.data.datasets[0].data = h.t.map((t, i) => ({ x: t - latest, y: h.id[i] }));
    chart.data.datasets[1].data = h.t.map((t, i) => ({ x: t - latest, y: h.model[i] }));
    chart.update("none");
  }
  // Coordinates of another pack (the exercise changed) are hidden, not deleted: they come back with it.
  for (const [coordinate, chart] of Object.entries(charts.torques)) chart.wrap.hidden = !(coordinate in history);
}

// ---- traces: the last 10 s of the chosen muscles -----------------------------------------------------------------
function recordTraces(method, frame) {
  const byGroup = (state.traces[method] = state.traces[method] || {});
  frame.groups.forEach((g, i) => {
    let h = byGroup[g];
    if (!h || (h.t.length && frame.time_s < h.t[h.t.length - 1])) h = byGroup[g] = { t: [], a: [], lo: [], hi: [], e: [] };
    const a = frame.activations[i], s = frame.std.length === frame.groups.length ? frame.std[i] : null;
    h.t.push(frame.time_s);
    h.a.push(a);
    h.lo.push(a === null || s === null ? null : Math.max(0, a - s));
    h.hi.push(a === null || s === null ? null : Math.min(1, a + s));
    h.e.push(frame.envelope && frame.envelope.length === frame.groups.length ? frame.envelope[i] : null);
    while (h.t.length && h.t[0] < frame.time_s - TRACE_WINDOW_S) for (const k of ["t", "a", "lo", "hi", "e"]) h[k].shift();
  });
}

// A rep starts where the phase enters [0, 1) or wraps (the rule of msk_core.signal.reps.PhaseRepCounter); a new set
// (the set number of the reps entry) starts the overlay again.
function recordRepOverlay(method, frame) {
  const o = (state.repOverlay[method] = state.repOverlay[method] || { set: null, lastPhase: null, reps: [] });
  const set = state.reps ? state.reps.set : null;
  if (set !== o.set) { o.set = set; o.reps = []; o.lastPhase = null; }
  const p = frame.phase;
  if (p === null || p === undefined || p < 0) { o.lastPhase = null; return; }
  if (o.lastPhase === null || p < o.lastPhase - 0.5) {
    o.reps.push({});
    if (o.reps.length > REP_OVERLAY_COUNT) o.reps.shift();
  }
  o.lastPhase = p;
  const rep = o.reps[o.reps.length - 1];
  frame.groups.forEach((g, i) => {
    if (frame.activations[i] !== null) (rep[g] = rep[g] || []).push({ x: 100 * p, y: 100 * frame.activations[i] });
  });
}

// The chosen muscles' reps, each in its muscle's colour, older reps fainter and thinner.
function repOverlayDatasets(method, chosen) {
  const o = state.repOverlay[method];
  if (!o) return [];
  const n = o.reps.length, out = [];
  chosen.forEach((g, k) => {
    const colour = TRACE_COLOURS[k % TRACE_COLOURS.length];
    o.reps.forEach((rep, r) => {
      if (!rep[g]) return;
      const alpha = Math.round(255 * (0.2 + 0.8 * (r + 1) / n)).toString(16).padStart(2, "0");
      out.push({ label: `${shortName(g)} rep ${r + 1 - n}`, data: rep[g], borderColor: colour + alpha, borderWidth: r === n - 1 ? 3 : 1.5, pointRadius: 0, fill: false, group: g });
    });
  });
  return out;
}

// The default muscles: the first ones with a measured envelope (an electrode), else the first of the pack.
function tracedGroups(frame) {
  if (state.traceGroups) return state.traceGroups.filter((g) => frame.groups.includes(g));
  const measured = frame.groups.filter((g, i) => frame.envelope && frame.envelope[i] !== null && frame.envelope[i] !== undefined);
  return (measured.length ? measured : frame.groups).slice(0, TRACE_DEFAULT_COUNT);
}
// A muscle in few words: "Deltoid, anterior part" -> "Deltoid anterior" (the full name in the tooltip).
function shortName(group) {
  const name = groupName(group), comma = name.indexOf(", ");
  return comma > 0 ? `${name.slice(0, comma).split(" ")[0]} ${name.slice(comma + 2).split(" ")[0]}` : name;
}

function renderTraceChips(frame, chosen) {
  const box = document.getElementById("trace-groups");
  const key = frame.groups.join(",") + "|" + chosen.join(",") + "|" + (state.session ? JSON.stringify(state.session.names) : "");
  if (box.dataset.key === key) return;
  box.dataset.key = key;
  box.replaceChildren(...frame.groups.map((g) => {
    const chip = document.createElement("button");
    chip.type = "button";
    chip.className = "chip";
    chip.dataset.group = g;
    const k = chosen.indexOf(g);
    if (k >= 0) { chip.classList.add("on"); chip.style.borderColor = chip.style.background = TRACE_COLOURS[k % TRACE_COLOURS.length]; }
    chip.textContent = shortName(g);
    chip.title = groupName(g);
    chip.addEventListener("click", () => {
      const now = tracedGroups(frame);
      state.traceGroups = now.includes(g) ? now.filter((x) => x !== g) : [...now, g].slice(-TRACE_COLOURS.length);
      scheduleRender();
    });
    return chip;
  }));
}

function renderTraces(method, frame) {
  const chosen = tracedGroups(frame);
  renderTraceChips(frame, chosen);
  if (state.traceMode === "reps") { drawTraces(repOverlayDatasets(method, chosen)); return; }
  const history = state.traces[method] || {};
  let latest = -Infinity;
  for (const g of chosen) { const h = history[g]; if (h && h.t.length) latest = Math.max(latest, h.t[h.t.length - 1]); }
  const datasets = [];
  chosen.forEach((g, k) => {
    const h = history[g];
    if (!h) return;
    const colour = TRACE_COLOURS[k % TRACE_COLOURS.length];
    const points = (values) => h.t.map((t, i) => ({ x: t - latest, y: values[i] === null ? null : 100 * values[i] }));
    datasets.push(
      { label: `${shortName(g)} −σ`, data: points(h.lo), borderWidth: 0, pointRadius: 0, fill: false, group: g },
      { label: `${shortName(g)} ±σ`, data: points(h.hi), borderWidth: 0, pointRadius: 0, fill: "-1", backgroundColor: colour + "33", group: g },
      { label: shortName(g), data: points(h.a), borderColor: colour, borderWidth: 2.5, pointRadius: 0, fill: false, group: g },
    );
    if (h.e.some((v) => v !== null)) {
      datasets.push({ label: `${shortName(g)} EMG`, data: points(h.e), borderColor: colour, borderWidth: 2, borderDash: [6, 4], pointRadius: 0, fill: false, spanGaps: false, group: g });
    }
  });
  drawTraces(datasets);
}

// The one chart of both modes: x in s before the newest frame, or in % of the rep.
function drawTraces(datasets) {
  const reps = state.traceMode === "reps";
  const x = reps
    ? { type: "linear", min: 0, max: 100, ticks: { stepSize: 25, font: { size: 18 }, color: "#1d2630", callback: (v) => `${v}%` } }
    : { type: "linear", min: -TRACE_WINDOW_S, max: 0, ticks: { stepSize: 2, font: { size: 18 }, color: "#1d2630", callback: (v) => `${v.toFixed(0)} s` } };
  if (!charts.traces) {
    charts.traces = new Chart(document.getElementById("traces"), {
      type: "line",
      data: { datasets },
      options: {
        animation: false, responsive: true, maintainAspectRatio: false, parsing: false, normalized: true,
        scales: { x, y: { min: 0, max: 100, ticks: { stepSize: 25, font: { size: 18 }, color: "#1d2630", callback: (v) => `${v}%` } } },
        plugins: { legend: { display: false }, tooltip: { enabled: false } },
      },
    });
    return;
  }
  if (charts.traces.mode !== state.traceMode) { charts.traces.options.scales.x = x; charts.traces.mode = state.traceMode; }
  charts.traces.data.datasets = datasets;
  charts.traces.update("none");
}
for (const mode of ["time", "reps"]) {
  document.getElementById(`trace-${mode}`).addEventListener("click", () => {
    state.traceMode = mode;
    for (const other of ["time", "reps"]) document.getElementById(`trace-${other}`).classList.toggle("on", other === mode);
    document.getElementById("trace-hint").textContent = mode === "reps"
      ? `the set's last ${REP_OVERLAY_COUNT} reps on rep time, the newest bold`
      : "line estimate, shade ± uncertainty, dashed measured EMG envelope";
    scheduleRender();
  });
}

// Electrode rows in the frame's muscle order (electrodes of no muscle in the frame last), by channel within a muscle.
function inMuscleOrder(electrodes, frame) {
  const order = frame ? frame.groups : [];
  const rank = (e) => (order.includes(e.group) ? order.indexOf(e.group) : order.length);
  return [...electrodes].sort((a, b) => rank(a) - rank(b) || a.channel.localeCompare(b.channel));
}

// ---- fatigue: per electrode the median frequency of each rep and its trend over the set -------------------------
function renderFatigue(frame) {
  const rows = inMuscleOrder(state.fatigue, frame).map((e) => {
    const tr = document.createElement("tr");
    tr.dataset.channel = e.channel;
    const reps = e.median_hz.length;
    const last = reps ? e.median_hz[reps - 1] : null;
    const change = e.median_change_pct;
    tr.dataset.reps = reps;
    tr.className = e.tiring ? "tiring" : ""; // msk_core.estimate.fatigue_verdict.tiring: 3+ reps, -10 %, a falling trend
    tr.title = `median frequency per rep (Hz): ${e.median_hz.map((v) => (v === null ? "–" : v.toFixed(0))).join(", ")}`
      + (e.mean_change_pct === null ? "" : `; mean frequency ${e.mean_change_pct.toFixed(1)} % since the set's first reps`);
    tr.innerHTML = `<td title="${escapeHtml(e.group ? groupName(e.group) : e.channel)}">${escapeHtml(e.group ? shortName(e.group) : e.channel)}</td><td>${reps}</td>`
      + `<td>${fmt(last, 0, " Hz")}</td><td>${signedPercent(e.median_slope_pct_per_rep, 1)}</td>`
      + `<td class="change">${signedPercent(change)}</td>`;
    return tr;
  });
  document.querySelector("#fatigue tbody").replaceChildren(...rows);
  const set = state.fatigue.length ? state.fatigue[0].set_number : 0;
  document.getElementById("fatigue-set").textContent = set ? `set ${set}` : "";
  document.getElementById("fatigue-panel").hidden = rows.length === 0;
}

// "+1.2 %", "−3 %", "0 %" (no "-0"); "–" for no value.
function signedPercent(v, digits = 0) {
  if (v === null || v === undefined) return "–";
  const text = Math.abs(v).toFixed(digits);
  return Number(text) === 0 ? `${text} %` : `${v > 0 ? "+" : "−"}${text} %`;
}

function fmt(v, digits = 1, unit = "") { return v === null || v === undefined ? "–" : `${v.toFixed(digits)}${unit}`; }

function renderDevices(frame) {
  const rows = Object.entries(state.devices).sort().map(([name, d]) => {
    const ok = d.delivering && d.connected !== false;
    const stateText = d.connected === false ? "disconnected" : d.delivering ? "delivering" : "silent";
    const tr = document.createElement("tr");
    tr.dataset.device = name;
    tr.innerHTML = `<td>${escapeHtml(name)}<br><span class="hint">${escapeHtml(d.kind)}${d.segment ? " · " + escapeHtml(d.segment) : ""}</span></td>`
      + `<td class="${ok ? "ok" : "bad"}">${stateText}</td>`
      + `<td>${d.samples}</td><td class="${d.samples_lost ? "bad" : ""}">${d.samples_lost}</td><td>${fmt(d.latency_ms, 1, " ms")}</td>`;
    return tr;
  });
  document.querySelector("#devices tbody").replaceChildren(...rows);
  const info = document.getElementById("estimator");
  info.textContent = frame
    ? `estimator ${frame.method}: ${frame.solver_status}${frame.flags.length ? " (" + frame.flags.join(", ") + ")" : ""}, `
      + `solve+publish ${fmt(frame.estimator_latency_ms, 2, " ms")}, to this page ${fmt(frame.transport_latency_ms, 1, " ms")}`
    : "";
}

function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
}

// Each node's own status (DeviceStatus kind "node") and this dashboard's bridge: inputs dropped, per topic and reason.
function renderNodes() {
  const rows = Object.entries(state.nodes).sort().map(([name, n]) => {
    const tr = document.createElement("tr");
    tr.dataset.node = name;
    tr.title = n.drops.map(([key, reason, count]) => `${key}: ${reason} ${count}`).join("\n");
    tr.innerHTML = `<td>${escapeHtml(name)}</td><td class="${n.running ? "ok" : "bad"}">${n.running ? "running" : "stopped"}</td>`
      + `<td>${n.received}</td><td class="${n.dropped ? "bad" : ""}">${n.dropped}</td>`;
    return tr;
  });
  document.querySelector("#nodes tbody").replaceChildren(...rows);
}

// Each electrode's signal quality under its muscle's name, in the frame's muscle order: good, check or bad with the
// reason (the verdict with its numbers as the row's tooltip).
function renderElectrodes(frame) {
  const rows = inMuscleOrder(state.electrodes, frame).map((e) => {
    const tr = document.createElement("tr");
    tr.dataset.channel = e.channel;
    tr.dataset.state = e.state;
    tr.title = e.detail;
    const reasons = e.reasons.length ? ": " + e.reasons.join(", ") : "";
    const muscle = e.group ? groupName(e.group) : "(no muscle)"; // in few words, the whole name in the tooltip
    tr.innerHTML = `<td title="${escapeHtml(muscle)}">${escapeHtml(e.group ? shortName(e.group) : muscle)}</td>`
      // the sensor by its number ("#9" for sensor09.EMG, the channel in the tooltip): room for the state's reason
      + `<td class="hint" title="${escapeHtml(e.channel)}">${escapeHtml(e.channel.split(".")[0].replace(/^sensor0*(?=\d)/, "#"))}</td>`
      + `<td class="q-${escapeHtml(e.state)}">${escapeHtml(e.state + reasons)}</td>`;
    return tr;
  });
  document.querySelector("#electrodes tbody").replaceChildren(...rows);
  document.getElementById("electrodes-title").hidden = rows.length === 0;
}

// Sets: one column per set (the newest 3), rows: reps, time under tension, then peak / mean % per muscle group.
function renderSets() {
  // the figures are of one method (the report's), whichever the menu shows: say which
  const figuresOf = state.session && state.session.set_figures_method;
  document.getElementById("sets-hint").textContent =
    "reps · time under tension · peak / mean activation %" + (figuresOf ? ` of ${figuresOf}` : "");
  const sets = (state.sets || []).slice(-3);
  const head = document.querySelector("#sets thead"), body = document.querySelector("#sets tbody");
  const pct = (v) => (v === null || v === undefined ? "–" : (100 * v).toFixed(0));
  head.replaceChildren(...(sets.length ? [tableRow("th", ["", ...sets.map((s) => `set ${s.number}`)])] : []));
  if (!sets.length) { body.replaceChildren(); return; }
  const withFrames = sets.filter((s) => s.groups.length); // a set just started has no frames yet
  const groups = withFrames.length ? withFrames[withFrames.length - 1].groups : [];
  const rows = [
    tableRow("td", ["reps", ...sets.map((s) => String(s.reps))]),
    tableRow("td", ["under tension", ...sets.map((s) => `${s.time_under_tension_s.toFixed(1)} s`)]),
    ...groups.map((g) => tableRow("td", [groupName(g), ...sets.map((s) => {
      const i = s.groups.indexOf(g);
      return i < 0 ? "–" : `${pct(s.peak[i])} / ${pct(s.mean[i])}`;
    })])),
  ];
  body.replaceChildren(...rows);
}
function tableRow(cell, texts) {
  const row = document.createElement("tr");
  row.replaceChildren(...texts.map((text) => { const c = document.createElement(cell); c.textContent = text; return c; }));
  return row;
}
// The operator's buttons: POST /set/start or /set/stop publishes the session fact (as `msk set start|stop`).
function setMark(mark) {
  const reply = document.getElementById("set-reply");
  fetch(`/set/${mark}`, { method: "POST" }).then((r) => r.json()).then((answer) => {
    reply.textContent = answer.error ? answer.error : (mark === "start" ? `set ${answer.set_number} started` : "set ended");
    reply.title = reply.textContent; // the reply is clamped to two lines in the header; whole on hover
  }).catch((error) => { reply.textContent = `not sent: ${error}`; reply.title = reply.textContent; });
}
document.getElementById("set-start").addEventListener("click", () => setMark("start"));
document.getElementById("set-stop").addEventListener("click", () => setMark("stop"));
// A dashboard whose role may not publish the session's facts offers no buttons that the router would refuse: they
// are disabled, the reason in their tooltip and in the reply's.
function showSetMarks(refused) {
  for (const id of ["set-start", "set-stop"]) {
    const button = document.getElementById(id);
    button.disabled = Boolean(refused);
    button.title = refused ? `this dashboard cannot mark sets: ${refused}` : "";
  }
  const reply = document.getElementById("set-reply");
  reply.textContent = refused ? "view only: sets are marked at the rack" : "";
  reply.title = refused || "";
}

// The configuration is fetched again on every (re)connection: a restarted dashboard may serve another session.
function start() {
  fetch("/config.json", { cache: "no-store" }).then((r) => {
    if (r.status === 401) { withdrawn(); return null; } // the token is no longer valid: no retry
    return r.json();
  }).then((config) => {
    if (config === null) return;
    state.config = config;
    const session = document.getElementById("session"); // the name alone (room in the header), "session" on hover
    session.textContent = config.session;
    session.title = `session ${config.session} (msk/${config.session}/...)`;
    showSetMarks(config.set_marks_refused);
    connect();
  }).catch(() => {
    state.connection = state.connection === "connecting" ? "connecting" : "reconnecting";
    scheduleRender();
    setTimeout(start, state.reconnectMs);
    state.reconnectMs = Math.min(state.reconnectMs * 2, RECONNECT_MAX_MS);
  });
}
start();
