// hydrolens dashboard, condition panel: per drive with condition checks enabled, the trend of each fitted effect
// parameter across checks (/api/drives/{name}/condition), its limit, the checks after which the effect was in alarm
// marked in red, the alarms raised now, and when the last check ran. Refreshed every REFRESH_MS.
// Each tracked effect (one with a limit) is drawn in its own units under a human title, with its limit, the
// least-squares trend line and the projected crossing (/api/status drives[].condition[].trend), and a check that
// found nothing drawn as a grey point at the nominal value ("checked, nothing found"). Above the charts, where the
// power goes since the start (drives[].energy): load, friction, leakage and slip as shares of the input power, or,
// where the drive's output power is read, of the drive's output, with the motor's own losses beside them and the
// overall efficiency.
// Test hooks: each panel carries data-drive, data-checks (checks shown) and data-alarms (alarms raised); each chart
// box data-parameter ("effect.parameter"), data-points (checks that named it), data-nothing-found (checks that did
// not), data-alarm-marks (checks marked), data-y-ticks (the value axis's labels, "|" apart), data-state (the trend's state) and data-crossing-unix-s; .last-check
// carries data-t-s (the last check's service time); each .flow of the power bar data-flow and data-share; the
// .power-flow box data-base ("input" or "drive") and data-overall-efficiency (empty where not read).
"use strict";

(function () {
  const REFRESH_MS = 2000;
  const panels = new Map(); // drive -> { section, charts: Map(key -> {box, plot}) }

  function fmtNum(v) {
    if (v === null || v === undefined || !Number.isFinite(v)) return "–";
    const a = Math.abs(v);
    return a !== 0 && (a < 0.01 || a >= 1e5) ? v.toExponential(3) : v.toPrecision(4);
  }

  /// Axis numbers in full, thousands apart by a thin space (15 000 bar, not a cut "5,000"), small ones as fmtNum.
  function fmtAxis(v) {
    if (v === null || !Number.isFinite(v)) return "";
    const a = Math.abs(v);
    if (a >= 1000) return Math.round(v).toString().replace(/\B(?=(\d{3})+(?!\d))/g, "\u2009");
    return a !== 0 && a < 0.01 ? v.toExponential(1) : String(+v.toPrecision(3));
  }

  // Each catalogue parameter: a title a user reads, and its unit.
  const TITLES = {
    "internal_leakage.l_min_per_bar": ["Internal leakage", "l/min/bar"],
    "entrained_air.bulk_modulus_bar": ["Entrained air: effective bulk modulus", "bar"],
    "dead_time.ms": ["Dead time", "ms"],
    "coulomb_friction.torque_nm": ["Dry (Coulomb) friction", "N·m"],
    "stribeck_friction.breakaway_nm": ["Stribeck friction: breakaway torque", "N·m"],
    "stribeck_friction.speed_rad_s": ["Stribeck friction: speed", "rad/s"],
    "torque_offset.torque_nm": ["Torque offset", "N·m"],
    "motor_slip.rpm_per_nm": ["Motor slip", "rpm/N·m"],
  };

  function title(key) {
    const t = TITLES[key];
    return t ? `${t[0]} (${t[1]})` : key;
  }

  function fmtDuration(s) {
    if (!Number.isFinite(s)) return "open";
    if (s < 120) return `${s.toFixed(0)} s`;
    if (s < 7200) return `${(s / 60).toFixed(0)} min`;
    if (s < 2 * 86400) return `${(s / 3600).toFixed(1)} h`;
    return `${(s / 86400).toFixed(1)} days`;
  }

  /// The trend's state in words, with the projected crossing and its interval.
  function trendText(t) {
    if (!t) return "";
    const tr = t.trend;
    switch (tr.state) {
      case "rising":
        return `rising: reaches the limit in ${fmtDuration(tr.seconds_to_limit)} ` +
          `(95 %: ${fmtDuration(tr.seconds_to_limit_low)} … ${fmtDuration(tr.seconds_to_limit_high ?? Infinity)}), ` +
          `${fmtTime(t.crossing_unix_s)}`;
      case "past_limit": return "past the limit";
      case "not_rising": return "not rising";
      default: return "too few checks for a trend (4 needed)";
    }
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
    const w = Math.max(360, Math.min(560, (document.body.clientWidth - 80) / 3));
    const none = () => null;
    const opts = {
      title: title(key), width: Math.floor(w), height: 220,
      scales: { x: { time: true } },
      axes: [{}, { size: 64, values: (u, vals) => {
        const labels = vals.map(fmtAxis);
        box.dataset.yTicks = labels.join("|");
        return labels;
      } }],
      series: [
        {},
        { label: "fitted", stroke: "#1565c0", width: 1.5, points: { show: true, size: 5 } },
        { label: "limit", stroke: "#c62828", width: 1, dash: [6, 4], points: { show: false }, spanGaps: true },
        { label: "in alarm", stroke: "#c62828", width: 0, paths: none, points: { show: true, size: 9, fill: "#c62828" } },
        { label: "checked, nothing found", stroke: "#8a929e", width: 0, paths: none, points: { show: true, size: 6, fill: "#fff" } },
        { label: "trend", stroke: "#ef6c00", width: 1.5, dash: [3, 3], points: { show: false }, spanGaps: true },
        { label: "projected crossing", stroke: "#ef6c00", width: 0, paths: none, points: { show: true, size: 11, fill: "#ef6c00" } },
      ],
    };
    const caption = document.createElement("p");
    caption.className = "trend muted";
    c = { box, caption, plot: new uPlot(opts, [[], [], [], [], [], [], []], box) };
    box.appendChild(caption);
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
    const tracked = new Map((c.tracked || []).map(t => [`${t.effect}.${t.parameter}`, t]));
    for (const [effect, parameter] of parameters(c)) {
      drawParameter(panel, checks, c, effect, parameter, tracked.get(`${effect}.${parameter}`));
    }
  }

  /// One parameter's chart: the checks at their windows' centres, the limit, the trend line from the first check to
  /// the projected crossing (or the last check), and the crossing itself.
  function drawParameter(panel, checks, c, effect, parameter, t) {
    const chart = chartFor(panel, effect, parameter);
    const limit = c.limits && c.limits[effect] ? c.limits[effect][parameter] : undefined;
    const nominal = t ? t.nominal : null;
    const rows = [];
    for (const ch of checks) {
      const f = (ch.findings || []).find(f => f.effect === effect);
      const v = f && f.parameters ? f.parameters[parameter] : undefined;
      const found = Number.isFinite(v);
      rows.push([ch.unix_s - ch.window_s / 2, found ? v : null, !found && Number.isFinite(nominal) ? nominal : null,
        (ch.alarms || []).includes(effect) && found ? v : null]);
    }
    const last = checks[checks.length - 1];
    const tr = t && t.trend;
    const line = x => tr && Number.isFinite(tr.value_now) && last
      ? tr.value_now + tr.slope_per_day / 86400 * (x - last.unix_s) : null;
    const crossing = t && Number.isFinite(t.crossing_unix_s) && tr.state === "rising" ? t.crossing_unix_s : null;
    if (crossing !== null) rows.push([crossing, null, null, null]);
    rows.sort((a, b) => a[0] - b[0]);
    const drawsTrend = tr && (tr.state === "rising" || tr.state === "past_limit" || tr.state === "not_rising");
    const xs = rows.map(r => r[0]);
    chart.plot.setData([
      xs,
      rows.map(r => r[1]),
      xs.map(() => (Number.isFinite(limit) ? limit : null)),
      rows.map(r => r[3]),
      rows.map(r => r[2]),
      xs.map(x => (drawsTrend ? line(x) : null)),
      xs.map(x => (x === crossing ? limit : null)),
    ]);
    chart.box.dataset.points = String(rows.filter(r => r[1] !== null).length);
    chart.box.dataset.nothingFound = String(rows.filter(r => r[2] !== null).length);
    chart.box.dataset.alarmMarks = String(rows.filter(r => r[3] !== null).length);
    chart.box.dataset.state = tr ? tr.state : "";
    chart.box.dataset.crossingUnixS = crossing !== null ? String(crossing) : "";
    const now = t && !t.found && last ? "checked, nothing found · " : "";
    chart.caption.textContent = `${now}limit ${fmtNum(limit)} · ${trendText(t)}`;
  }

  // The power bar: each flow as a share of the input power since the start, or of the drive's output where it is
  // read (then the motor's copper and iron losses, drive output less input, are a flow of their own).
  const FLOWS = [
    ["load_w", "load", "#2e7d32"],
    ["viscous_w", "viscous friction", "#f9a825"],
    ["dry_friction_w", "dry friction", "#ef6c00"],
    ["leakage_w", "leakage (nominal)", "#64b5f6"],
    ["internal_leakage_w", "internal leakage", "#1565c0"],
    ["slip_w", "motor slip", "#8e24aa"],
  ];

  function drawEnergy(panel, e) {
    let box = panel.section.querySelector(".power-flow");
    if (!box) {
      box = document.createElement("div");
      box.className = "power-flow";
      box.innerHTML = `<h4>Where the power goes</h4><div class="bar"></div><p class="muted legend"></p>`;
      panel.section.insertBefore(box, panel.section.querySelector(".chart-row"));
    }
    const input = e.energy_j.input_w;
    const drive = e.drive_energy_j;
    const byDrive = Number.isFinite(drive) && drive > 0;
    const base = byDrive ? drive : input;
    const energies = { ...e.energy_j, motor_w: byDrive ? drive - input : 0 };
    const flows = byDrive ? [...FLOWS, ["motor_w", "motor (copper, iron)", "#6d4c41"]] : FLOWS;
    box.dataset.base = byDrive ? "drive" : "input";
    box.dataset.overallEfficiency = Number.isFinite(e.overall_efficiency) ? String(e.overall_efficiency) : "";
    const bar = box.querySelector(".bar");
    const parts = flows.map(([k, label, color]) => {
      const share = base > 0 ? Math.max(0, energies[k]) / base : 0;
      const d = document.createElement("span");
      d.className = "flow";
      d.dataset.flow = k.replace(/_w$/, "");
      d.dataset.share = share.toFixed(4);
      d.style.width = `${(100 * share).toFixed(2)}%`;
      d.style.background = color;
      d.title = `${label}: ${(100 * share).toFixed(1)} %`;
      d.textContent = share > 0.06 ? `${label} ${(100 * share).toFixed(0)} %` : "";
      d.style.paddingLeft = share > 0.06 ? "0.3em" : "0";
      return d;
    });
    bar.replaceChildren(...parts);
    const eff = v => (Number.isFinite(v) ? `${(100 * v).toFixed(1)} %` : "–");
    const cost = (e.effects || []).map(x => `${x.effect.replace(/_/g, " ")} ${fmtNum(x.power_w)} W, ` +
      `${fmtNum(x.kwh_per_day)} kWh/day` + (Number.isFinite(x.cost_per_year) ? `, ${fmtNum(x.cost_per_year)} a year` : ""));
    const overall = byDrive
      ? `drive output ${fmtNum(e.drive_power_w)} W now, overall efficiency ${eff(e.overall_efficiency)} · `
      : "overall efficiency: the drive's output power is not read · ";
    box.querySelector(".legend").textContent = overall +
      `input ${fmtNum(e.power_w.input_w)} W now, ${fmtNum(input / 3.6e6)} kWh over ${fmtDuration(e.span_s)} · ` +
      `volumetric efficiency ${eff(e.volumetric_efficiency)}, mechanical ${eff(e.mechanical_efficiency)}` +
      (cost.length ? ` · above the nominal model: ${cost.join("; ")}` : " · nothing above the nominal model");
  }

  async function refresh(names) {
    let energy = new Map();
    try {
      const status = await (await fetch("/api/status")).json();
      energy = new Map(status.drives.map(d => [d.name, d.energy]));
    } catch (err) {
      console.error(err);
    }
    for (const name of names) {
      try {
        const r = await fetch(`/api/drives/${encodeURIComponent(name)}/condition`);
        if (!r.ok) continue;
        const c = await r.json();
        if (c.enabled || c.checks.length > 0) render(c);
        const e = energy.get(name);
        if (e && panels.has(name)) drawEnergy(panels.get(name), e);
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
