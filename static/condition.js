// hydrolens dashboard, condition panel: per drive with condition checks enabled, the trend of each fitted effect
// parameter across checks (/api/drives/{name}/condition), its limit, the checks after which the effect was in alarm
// marked in red, the alarms raised now, and when the last check ran. Refreshed every REFRESH_MS.
// Test hooks: each panel carries data-drive, data-checks (checks shown) and data-alarms (alarms raised); each chart
// box data-parameter ("effect.parameter"), data-points and data-alarm-marks (checks marked); .last-check carries
// data-t-s (the last check's service time).
"use strict";

(function () {
  const REFRESH_MS = 10000;
  const panels = new Map(); // drive -> { section, charts: Map(key -> {box, plot}) }

  function fmtNum(v) {
    if (v === null || v === undefined || !Number.isFinite(v)) return "–";
    const a = Math.abs(v);
    return a !== 0 && (a < 0.01 || a >= 1e5) ? v.toExponential(3) : v.toPrecision(4);
  }

  function fmtTime(unixS) {
    return unixS > 0 ? new Date(unixS * 1000).toLocaleString() : "–";
  }

  function makePanel(name) {
    const section = document.createElement("div");
    section.className = "condition-panel";
    section.dataset.drive = name;
    section.innerHTML = `<h3></h3><p class="muted"><span class="last-check" data-t-s=""></span></p>
      <ul class="alarms"></ul><div class="chart-row"></div>`;
    section.querySelector("h3").textContent = `${name}: condition`;
    document.getElementById("condition").appendChild(section);
    const p = { section, charts: new Map() };
    panels.set(name, p);
    return p;
  }

  /// The (effect, parameter) pairs to draw: those with a limit, then any other a check fitted.
  function parameters(c) {
    const keys = [];
    const add = (e, p) => { if (!keys.some(k => k[0] === e && k[1] === p)) keys.push([e, p]); };
    for (const [e, ps] of Object.entries(c.limits || {})) for (const p of Object.keys(ps)) add(e, p);
    for (const ch of c.checks) for (const f of ch.findings || []) for (const p of Object.keys(f.parameters || {})) add(f.effect, p);
    return keys;
  }

  function chartFor(panel, effect, parameter) {
    const key = `${effect}.${parameter}`;
    let c = panel.charts.get(key);
    if (c) return c;
    const box = document.createElement("div");
    box.className = "chart condition-chart";
    box.dataset.parameter = key;
    box.dataset.points = "0";
    box.dataset.alarmMarks = "0";
    panel.section.querySelector(".chart-row").appendChild(box);
    const w = Math.max(320, Math.min(560, (document.body.clientWidth - 80) / 3));
    const opts = {
      title: key, width: Math.floor(w), height: 200,
      scales: { x: { time: true } },
      series: [
        {},
        { label: "fitted", stroke: "#1565c0", width: 1.5, points: { show: true, size: 5 } },
        { label: "limit", stroke: "#c62828", width: 1, dash: [6, 4], points: { show: false } },
        { label: "in alarm", stroke: "#c62828", width: 0, paths: () => null, points: { show: true, size: 9, fill: "#c62828" } },
      ],
    };
    c = { box, plot: new uPlot(opts, [[], [], [], []], box) };
    panel.charts.set(key, c);
    return c;
  }

  function render(c) {
    const panel = panels.get(c.drive) || makePanel(c.drive);
    const checks = c.checks;
    panel.section.dataset.checks = String(checks.length);
    panel.section.dataset.alarms = String(c.alarms.length);
    const last = checks[checks.length - 1];
    const lastEl = panel.section.querySelector(".last-check");
    lastEl.dataset.tS = last ? String(last.t_s) : "";
    lastEl.textContent = last
      ? `last check ${fmtTime(last.unix_s)} (service time ${last.t_s.toFixed(0)} s, ${last.window_s.toFixed(0)} s of data, ` +
        `${last.duration_s.toFixed(2)} s to run) · ${checks.length} checks` + (c.last_error ? ` · last attempt failed: ${c.last_error}` : "")
      : "no check yet" + (c.last_error ? ` · last attempt failed: ${c.last_error}` : "");
    const ul = panel.section.querySelector(".alarms");
    ul.replaceChildren(...c.alarms.map(a => {
      const li = document.createElement("li");
      li.className = "alarm";
      li.dataset.effect = a.effect;
      li.textContent = `ALARM ${a.effect}: ${a.parameter} = ${fmtNum(a.value)} (limit ${fmtNum(a.limit)}) since ${fmtTime(a.since_unix_s)}`;
      return li;
    }));
    for (const [effect, parameter] of parameters(c)) {
      const chart = chartFor(panel, effect, parameter);
      const limit = c.limits && c.limits[effect] ? c.limits[effect][parameter] : undefined;
      const xs = [], ys = [], lim = [], marks = [];
      for (const ch of checks) {
        const f = (ch.findings || []).find(f => f.effect === effect);
        const v = f && f.parameters ? f.parameters[parameter] : undefined;
        xs.push(ch.unix_s);
        ys.push(Number.isFinite(v) ? v : null);
        lim.push(Number.isFinite(limit) ? limit : null);
        marks.push((ch.alarms || []).includes(effect) && Number.isFinite(v) ? v : null);
      }
      chart.plot.setData([xs, ys, lim, marks]);
      chart.box.dataset.points = String(ys.filter(v => v !== null).length);
      chart.box.dataset.alarmMarks = String(marks.filter(v => v !== null).length);
    }
  }

  async function refresh(names) {
    for (const name of names) {
      try {
        const r = await fetch(`/api/drives/${encodeURIComponent(name)}/condition`);
        if (!r.ok) continue;
        const c = await r.json();
        if (c.enabled || c.checks.length > 0) render(c);
      } catch (err) {
        console.error(err);
      }
    }
  }

  async function start() {
    try {
      const status = await (await fetch("/api/status")).json();
      const names = status.drives.map(d => d.name);
      await refresh(names);
      setInterval(() => refresh(names), REFRESH_MS);
    } catch (err) {
      console.error(err);
    }
  }

  start();
})();
