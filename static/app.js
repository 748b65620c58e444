// hydrolens dashboard: a card per drive and live charts, fed by /api/history once and /api/events (SSE) after.
// Test hooks: each card carries data-link (up, stale, tripped, down; unknown while the page has lost the service),
// data-mode, data-tripped; each chart box data-points (points plotted); the speed chart's box data-target-history
// (the lowest and highest target drawn from the history, "min max"; empty when none); #events data-events counts the
// snapshots received.
"use strict";

const WINDOW_S = 60;
// `?close_after=N` closes the event stream after N snapshots: a headless browser's virtual-time budget can then
// run out (an open stream counts as a pending fetch and holds virtual time still). Used by the dashboard test.
const CLOSE_AFTER = Number(new URLSearchParams(location.search).get("close_after")) || 0;
const drives = new Map(); // name -> { card, charts, data, lastT }
let eventCount = 0;

function fmt(v, digits) {
  return (v === null || v === undefined || !Number.isFinite(v)) ? "–" : v.toFixed(digits);
}

function linkState(d) {
  if (!d.link.connected) return "down";
  if (d.link.stale) return "stale";
  if (d.tripped) return "tripped";
  return "up";
}

function makeCard(d) {
  const card = document.createElement("article");
  card.className = "card";
  card.dataset.drive = d.name;
  card.innerHTML = `<h2><span class="name"></span><span class="badge link"></span><span class="badge mode"></span></h2>
    <dl>
      <dt>address</dt><dd class="address"></dd>
      <dt>ω measured</dt><dd class="omega"></dd>
      <dt>ω̂ estimated</dt><dd class="omega-hat"></dd>
      <dt>target</dt><dd class="target"></dd>
      <dt>T̂ load</dt><dd class="load"></dd>
      <dt>J inertia</dt><dd class="inertia"></dd>
      <dt>B viscous</dt><dd class="viscous"></dd>
      <dt>setpoint</dt><dd class="setpoint"></dd>
      <dt>p in / out</dt><dd class="pressures"></dd>
      <dt>status</dt><dd class="status"></dd>
      <dt>polls / errors / reconnects</dt><dd class="counts"></dd>
      <dt>loop jitter p50 / p99</dt><dd class="jitter"></dd>
    </dl>`;
  card.querySelector(".name").textContent = d.name;
  document.getElementById("cards").appendChild(card);
  return card;
}

function chartSize() {
  const w = Math.max(320, Math.min(560, (document.body.clientWidth - 80) / 3));
  return { width: Math.floor(w), height: 220 };
}

function makeChart(parent, title, series) {
  const box = document.createElement("div");
  box.className = "chart";
  box.dataset.points = "0";
  parent.appendChild(box);
  const opts = {
    title, ...chartSize(),
    scales: { x: { time: false } },
    axes: [{ label: "t (s)" }, {}],
    series: [{ label: "t_s" }, ...series.map(([label, stroke, dash]) => ({ label, stroke, width: 1.5, dash }))],
  };
  const data = [[], ...series.map(() => [])];
  const plot = new uPlot(opts, data, box);
  return { box, plot, data };
}

// The charts, each a list of series named by the recording's columns (what /api/history sends, and what a
// snapshot's `sample` and `estimate` carry, with the snapshot's target in speed mode).
const CHARTS = {
  pressure: ["pressures (bar)", [["p_in_bar", "p_in", "#c62828"], ["p_out_bar", "p_out", "#1565c0"]]],
  speed: ["speed (rad/s)", [["omega_rad_s", "ω measured", "#9e9e9e"], ["omega_hat_rad_s", "ω̂ estimated", "#1a7f37"],
    ["target_omega_rad_s", "target", "#000", [6, 4]]]],
  load: ["load (N·m) and setpoint (Hz)", [["load_hat_nm", "T̂ load", "#6a1b9a"], ["f_set_hz", "f set", "#ef6c00"],
    ["f_drive_hz", "f drive", "#0097a7"]]],
};

function makeDrive(d) {
  const section = document.createElement("div");
  section.className = "drive-charts";
  section.innerHTML = `<h3></h3><div class="chart-row"></div>`;
  section.querySelector("h3").textContent = d.name;
  document.getElementById("charts").appendChild(section);
  const row = section.querySelector(".chart-row");
  const charts = {};
  for (const [key, [title, series]] of Object.entries(CHARTS)) {
    charts[key] = makeChart(row, title, series.map(([, label, stroke, dash]) => [label, stroke, dash]));
    charts[key].columns = series.map(([column]) => column);
  }
  const entry = { card: makeCard(d), charts, lastT: -Infinity, historyT: -Infinity };
  drives.set(d.name, entry);
  return entry;
}

function finite(v) {
  return Number.isFinite(v) ? v : null;
}

/// Fills the charts with the last minute from the in-memory history ring: its columns are the charts' columns, the
/// speed target among them (as it was at each row: a target program's steps show in the history too).
async function loadHistory(entry, name) {
  const r = await fetch(`/api/history?drive=${encodeURIComponent(name)}&seconds=${WINDOW_S}&max_points=600`);
  if (!r.ok) return;
  const h = await r.json();
  const n = h.t_s.length;
  if (n === 0) return;
  for (const c of Object.values(entry.charts)) {
    c.data = [h.t_s.slice(), ...c.columns.map(col => (h[col] || new Array(n).fill(null)).map(finite))];
  }
  entry.lastT = entry.historyT = h.t_s[n - 1];
  redraw(entry);
}

/// Appends one point (an object holding the columns, as a snapshot's `sample` and `estimate` together are, and the
/// target).
function push(entry, p) {
  if (!p || !(p.t_s > entry.lastT)) return;
  entry.lastT = p.t_s;
  for (const c of Object.values(entry.charts)) {
    c.data[0].push(p.t_s);
    c.columns.forEach((col, i) => c.data[i + 1].push(finite(p[col])));
    while (c.data[0].length > 0 && c.data[0][0] < p.t_s - WINDOW_S) c.data.forEach(col => col.shift());
  }
}

function redraw(entry) {
  for (const c of Object.values(entry.charts)) {
    c.plot.setData(c.data);
    c.box.dataset.points = String(c.data[0].length);
  }
  // the target line as drawn (uPlot's own data), over the points that came from the history
  const speed = entry.charts.speed;
  const [t, target] = [speed.plot.data[0], speed.plot.data[1 + speed.columns.indexOf("target_omega_rad_s")]];
  const drawn = target.filter((v, i) => v !== null && t[i] <= entry.historyT);
  speed.box.dataset.targetHistory = drawn.length ? `${Math.min(...drawn)} ${Math.max(...drawn)}` : "";
}

// J and B count as identified once their standard deviation is within these fractions of the value
// (docs/estimator.md); a standard deviation of 0 means the method takes them from the model (kalman).
const J_IDENTIFIED_REL_SD = 0.1;
const B_IDENTIFIED_REL_SD = 0.3;

// `verdict` is the estimator's own word (`identification` in /api/status): its reason is shown whenever the value is
// not identified, so a user sees why (the load follows the speed, the nominal predicts as well, …).
function withConfidence(value, sd, unit, identifiedRelSd, verdict) {
  if (value === undefined || value === null || !Number.isFinite(value)) return "–";
  if (sd === 0) return `${fmt(value, 4)} ${unit} (from the model)`;
  const text = `${fmt(value, 4)} ± ${fmt(sd, 4)} ${unit}`;
  if (verdict && verdict.state !== "identified") return `${text} (${verdict.reason})`;
  return Math.abs(sd) <= identifiedRelSd * Math.abs(value) ? text : `${text} (not identified yet)`;
}

function updateCard(entry, d) {
  const card = entry.card;
  const q = sel => card.querySelector(sel);
  const state = linkState(d);
  card.classList.remove("lost");
  card.dataset.link = state;
  card.dataset.mode = d.mode;
  card.dataset.tripped = String(d.tripped);
  const link = q(".link");
  link.textContent = state;
  link.className = "badge link " + (state === "up" ? "ok" : state === "stale" ? "warn" : "bad");
  q(".mode").textContent = d.mode;
  q(".address").textContent = `${d.address} · unit ${d.unit_id}`;
  const s = d.sample, e = d.estimate;
  q(".omega").textContent = `${fmt(s && s.omega_rad_s, 2)} rad/s`;
  q(".omega-hat").textContent = `${fmt(e && e.omega_hat_rad_s, 2)} rad/s`;
  q(".target").textContent = d.mode === "speed" ? `${fmt(d.target_omega_rad_s, 2)} rad/s` : "–";
  const id = d.identification;
  const character = id && id.load_character !== "unknown" ? ` · ${id.load_character.replaceAll("_", " ")}` : "";
  q(".load").textContent = `${fmt(e && e.load_hat_nm, 2)} N·m${character}`;
  q(".inertia").textContent = withConfidence(e && e.inertia_hat_kg_m2, e && e.inertia_sd_kg_m2, "kg·m²",
    J_IDENTIFIED_REL_SD, id && id.inertia);
  q(".viscous").textContent = withConfidence(e && e.viscous_hat_nm_s_rad, e && e.viscous_sd_nm_s_rad, "N·m·s/rad",
    B_IDENTIFIED_REL_SD, id && id.viscous);
  q(".setpoint").textContent = `${fmt(d.setpoint_hz, 2)} Hz`;
  q(".pressures").textContent = `${fmt(s && s.p_in_bar, 1)} / ${fmt(s && s.p_out_bar, 1)} bar`;
  const st = d.status;
  q(".status").textContent = [st.ready && "ready", st.running && "running", st.fault && "FAULT",
    st.comm_loss_trip && "COMM-LOSS TRIP", st.not_following && "NOT FOLLOWING SETPOINTS",
    st.another_master && "ANOTHER MASTER WRITES THIS DRIVE: STOOD BACK",
    d.link.writes_failing && "WRITES REFUSED"].filter(Boolean).join(", ") || "–";
  q(".counts").textContent = `${d.link.polls} / ${d.link.errors} / ${d.link.reconnects}`;
  q(".jitter").textContent = `${fmt(d.timing.jitter_p50_ms, 2)} / ${fmt(d.timing.jitter_p99_ms, 2)} ms`;
}

// The page has lost the service (its event stream broke): what the cards show is old, so every card says so and
// greys its values until a snapshot comes again. A card left saying "up" would tell an operator the drive is fine.
function markLost() {
  for (const entry of drives.values()) {
    const card = entry.card;
    card.classList.add("lost");
    card.dataset.link = "unknown";
    const link = card.querySelector(".link");
    link.textContent = "no data";
    link.className = "badge link bad";
  }
}

function onSnapshot(status) {
  eventCount += 1;
  const ev = document.getElementById("events");
  ev.dataset.events = String(eventCount);
  ev.textContent = `${eventCount} updates`;
  const ready = document.getElementById("ready");
  ready.dataset.ready = String(status.ready);
  ready.textContent = status.ready ? "ready" : "not ready";
  ready.className = "badge " + (status.ready ? "ok" : "bad");
  document.getElementById("uptime").textContent = `up ${status.uptime_s.toFixed(0)} s`;
  for (const d of status.drives) {
    const entry = drives.get(d.name) || makeDrive(d);
    updateCard(entry, d);
    const target = d.mode === "speed" ? d.target_omega_rad_s : null;
    push(entry, d.sample && { ...d.sample, ...d.estimate, target_omega_rad_s: target });
    redraw(entry);
  }
}

function connect() {
  const es = new EventSource("/api/events");
  es.addEventListener("snapshot", m => {
    try { onSnapshot(JSON.parse(m.data)); } catch (err) { console.error(err); }
    if (CLOSE_AFTER && eventCount >= CLOSE_AFTER) {
      es.close();
      document.body.dataset.streamClosed = "true";
    }
  });
  es.onerror = () => {
    if (CLOSE_AFTER && eventCount >= CLOSE_AFTER) return;
    const ready = document.getElementById("ready");
    ready.textContent = "disconnected";
    ready.className = "badge bad";
    ready.dataset.ready = "false";
    markLost();
    // a refused stream (503: the service's stream cap) is closed for good by the browser: ask again later
    if (es.readyState === EventSource.CLOSED) {
      ready.textContent = "busy, retrying";
      setTimeout(connect, 5000 + Math.random() * 5000);
    }
  };
}

// history first, then live points strictly after it
async function init() {
  try {
    const status = await (await fetch("/api/status")).json();
    for (const d of status.drives) {
      const entry = makeDrive(d);
      updateCard(entry, d);
      await loadHistory(entry, d.name);
    }
  } catch (err) {
    console.error(err);
  }
  connect();
}

init();
