// Station overview page.
"use strict";
const $ = (id) => document.getElementById(id);
let last = null, seeking = false, selected = null, timelineKey = null, lastReplayed = null;

// A heading in [0, 360) with one decimal: 359.96 shows as 0.0, never 360.0.
function fmtHeading(v) {
  if (v === null || v === undefined) return "—";
  const r = Math.round((((v % 360) + 360) % 360) * 10) / 10;
  return (r >= 360 ? 0 : r).toFixed(1) + "°";
}

function fmtDate(unix) {
  return unix ? new Date(unix * 1000).toISOString().slice(0, 10) : "—";
}

// Headings for the plot, unwrapped: the first series (the attitude heading) continues across 0/360
// instead of jumping, every other one is drawn within ±180° of it (its own unwrap where the first
// has no value); the axis spans what is in view and its labels are read mod 360.
function unwrapHeadings(series) {
  const near = (v, r) => v + 360 * Math.round((r - v) / 360);
  let ref = null;
  const first = series[0].y.map((v) => (v === null || v === undefined ? null : (ref = ref === null ? v : near(v, ref))));
  return series.map((s, k) => {
    if (k === 0) return Object.assign({}, s, { y: first });
    let prev = null, r = null;
    return Object.assign({}, s, { y: s.y.map((v, i) => {
      if (first[i] !== null) r = first[i];
      if (v === null || v === undefined) return null;
      prev = near(v, first[i] !== null ? first[i] : (prev !== null ? prev : (r !== null ? r : v)));
      return prev;
    }) });
  });
}

// Heading axis: the unwrapped headings' own range (at least 20 deg), never a fixed 0..360.
function headingRange(series) {
  const v = series.flatMap((s) => s.y).filter((x) => x !== null && x !== undefined);
  if (!v.length) return { ymin: 0, ymax: 360 };
  const lo = Math.min(...v), hi = Math.max(...v);
  const pad = Math.max(5, (20 - (hi - lo)) / 2);
  return { ymin: lo - pad, ymax: hi + pad };
}

// Ticks of a heading axis: steps that read well mod 360 (5..90 deg), labels in [0, 360).
function headingTicks(lo, hi, count) {
  const step = [5, 10, 15, 30, 45, 90, 180].find((s) => (hi - lo) / s <= count + 1) || 180;
  const ticks = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi; v += step) ticks.push({ value: v, label: String(((v % 360) + 360) % 360) });
  return ticks;
}

function fmtSize(bytes) {
  return bytes >= 1e6 ? (bytes / 1e6).toFixed(1) + " MB" : Math.max(1, Math.round(bytes / 1e3)) + " kB";
}

const STATE_TEXT = { on: "on", off: "off", paused: "paused", untrusted: "untrusted", waiting: "waiting" };
const CORRECTION_TEXT = { station: "station-corrected", autopilot: "autopilot-corrected", raw: "raw (uncorrected)",
  unknown: "unknown", none: "no magnetometer" };

// The live link beside other ground stations: systems heard, the vehicle followed, passive mode,
// signing counts, forwarding outputs, compass parameters another station changed.
function renderLink(s) {
  const v = s.vehicles, live = s.source.kind === "live";
  setProp($("link-panel"), "hidden", !live || !v);
  if (!live || !v) return;
  setProp($("passive-note"), "hidden", !v.passive);
  setText($("passive-note"), v.passive ? "Listening only (" + (v.passive_reason || "passive mode") +
    "): MagStation sends nothing to the vehicle. Calibration writes need the active mode, or export the " +
    ".param file and load it with the other ground station." : "");
  const body = $("vehicles").tBodies[0];
  const rows = new Map([...body.rows].map((tr) => [tr.dataset.sysid, tr]));
  const heard = new Set(v.systems.map((x) => String(x.sysid)));
  for (const [id, tr] of rows) if (!heard.has(id)) { tr.remove(); rows.delete(id); }   // a new link
  for (const x of v.systems) {             // rows updated in place: the Follow button stays clickable
    let tr = rows.get(String(x.sysid));
    if (!tr) {
      tr = document.createElement("tr");
      tr.dataset.sysid = x.sysid;
      for (let i = 0; i < 8; i++) tr.append(document.createElement("td"));
      const b = document.createElement("button");
      b.textContent = "Follow";
      b.onclick = guarded("source-error", () => api("POST", "/api/vehicles/select", { sysid: x.sysid }));
      tr.cells[7].append(b);
      body.append(tr);
    }
    const cells = [x.sysid + (x.sysid === v.selected ? " ●" : ""), x.kind, x.type || "—", x.autopilot || "—",
      fmt(x.rate_hz, 0, " /s"), fmt(x.loss_pct, 1, " %"), fmt(x.last_seen_s, 1, " s ago")];
    cells.forEach((text, i) => setText(tr.cells[i], text));
    setProp(tr.cells[7].firstChild, "hidden", !(x.kind === "vehicle" && x.sysid !== v.selected));
  }
  const extra = [];
  if (v.signing && v.signing.on) extra.push("signing on (key " + v.signing.key_id + "): " + v.signing.good +
    " signed, " + v.signing.unsigned + " unsigned and " + v.signing.bad_signature + " badly signed refused");
  if (v.forwarding) extra.push("forwarding to " + v.forwarding.outputs.map((o) => o.url + " (" + o.to_gcs +
    " out, " + o.from_gcs + " in)").join(", ") + (v.forwarding.process && v.forwarding.process.error ?
    " — forwarding process stopped: " + v.forwarding.process.error : ""));
  const st = v.streams;     // the messages the station uses: missing ones and why (passive: the other station's)
  if (st && st.stale) extra.push("no attitude data: " + st.stale);
  if (st) extra.push(st.missing.length ? "missing: " + st.messages.filter((m) => m.state === "missing")
    .map((m) => m.name + " (" + m.why + ")").join(", ") : "all streams arriving" + (v.passive ? " (provided by the other station)" : ""));
  const changed = Object.keys(v.params_changed_elsewhere || {});
  if (changed.length) extra.push("changed by another ground station: " + changed.join(", "));
  setText($("link-extra"), extra.join(" · "));
}

function render(s) {
  last = s;
  setText($("status"), linkText(s) + (s.source.kind === "live" && s.reorder_delay_s >= 0.3 ?
    " — analysis " + fmt(s.reorder_delay_s, 1) + " s behind (late packets put back in time order)" : ""));
  const b = $("alarm-banner");
  if (s.alarm.active) {
    setProp(b, "className", "banner alarm");
    setText(b, "MAGNETIC INTERFERENCE ALARM" + (s.alarm.evidence_text ? ": " + s.alarm.evidence_text : "") +
      (s.alarm.since_s !== null ? " (since " + fmt(s.alarm.since_s, 1) + " s)" : ""));
  } else { setProp(b, "className", "banner ok"); setText(b, s.analysing ? "Analysing the log…" : "No interference alarm"); }
  renderVehicle(s);
  renderTests(s.tests);
  renderReplay(s);
  setProp($("pending"), "hidden", !s.source.pending);
  setText($("pending"), s.source.pending ? "connecting to " + s.source.pending + ": " + s.source.name +
    " goes on until the first packet arrives (Stop cancels)" : "");
  renderLink(s);
  renderInUse(s);
  setText($("line-text"), s.line ? "A " + s.line.a.map((x) => x.toFixed(6)).join(", ") + " → B " +
    s.line.b.map((x) => x.toFixed(6)).join(", ") + " (" + s.line.source + ")" : "none: no path-deviation test");
  setProp($("line-clear"), "disabled", !s.line);
  setText($("alarm-count"), s.alarm_count);
  const d = s.downloads;
  setText($("dl-log"), d.log ? "session log (" + d.log + ")" : "session log (none yet)");
  for (const id of ["dl-log", "dl-json", "dl-csv"]) $(id).classList.toggle("disabled", !d.log);
  setHtml($("events"), s.events.slice().reverse().map((e) =>
    `<div class="${e.level}">${fmt(e.t_s, 1)} s  ${escapeHtml(e.text)}</div>`).join(""));
}

const ATTITUDE_SOURCE_TEXT = {
  offline: "offline smoother (whole log, forward + backward; alarms use the causal AHRS)",
  causal: "causal AHRS",
};

function renderVehicle(s) {
  const v = s.vehicle, t = s.tests;
  setText($("v-rp"), fmt(v.roll_deg, 1, "°") + " / " + fmt(v.pitch_deg, 1, "°"));
  setText($("v-att-src"), ATTITUDE_SOURCE_TEXT[v.attitude_source] || "—");
  setText($("v-hdg"), fmtHeading(v.heading_att_deg) + " / " + fmtHeading(v.heading_mag_deg));
  setText($("v-aphdg"), fmtHeading(v.ap_yaw_deg));
  setText($("v-course"), (v.course_deg === null ? "— (not moving)" : fmtHeading(v.course_deg)) + " / " + fmt(v.speed_mps, 1, " m/s"));
  setText($("v-vel"), fmt(v.v_forward_mps, 2, " m/s") + " / " + fmt(v.v_lateral_mps, 2, " m/s"));
  setText($("v-xt"), fmt(v.cross_track_m, 2, " m"));
  setText($("v-field"), fmt(v.field_mG, 0, " mG") + " / " + fmt(v.inclination_deg, 1, "°"));
  setText($("v-cal"), CORRECTION_TEXT[t.field_correction.kind] || t.field_correction.kind);
  setProp($("v-cal"), "title", t.field_correction.note);
  setText($("v-pos"), v.lat_deg === null ? "—" : fmt(v.lat_deg, 6) + ", " + fmt(v.lon_deg, 6) + " / " + (v.fix_name || "fix " + v.fix_type));
  const untrusted = t.heading.state === "off" && t.field_correction.kind !== "none" && s.source.kind !== "none";
  setProp($("heading-caveat"), "hidden", !untrusted);
  setText($("heading-caveat"), untrusted ? "⚠ Heading test off: " + t.heading.why + "." : "");
  document.querySelector("#vehicle tr.hdg").classList.toggle("untrusted", untrusted);
}

function renderTests(tests) {
  for (const row of document.querySelectorAll("#tests tr")) {
    const st = tests[row.dataset.test];
    setText(row.querySelector(".state"), STATE_TEXT[st.state] || st.state);
    setProp(row.querySelector(".state"), "className", "state " + st.state);
    setText(row.querySelector(".why"), st.why);
  }
}

function renderReplay(s) {
  const r = s.replay;
  setProp($("replay-controls"), "hidden", !r);
  if (!r) { timelineKey = null; return; }
  if (s.source.name !== lastReplayed) {         // what plays changed: the list selects it
    lastReplayed = selected = s.source.name;
    for (const row of $("recordings").querySelectorAll("tr[data-name]")) row.classList.toggle("selected", row.dataset.name === selected);
  }
  setText($("pause"), r.paused ? "Resume" : "Pause");
  setProp($("seek"), "max", String(r.duration_s));
  if (!seeking) setProp($("seek"), "value", String(r.t_s));
  setText($("replay-time"), fmt(r.t_s, 1) + " / " + fmt(r.duration_s, 1) + " s ×" + r.speed + (r.finished ? " (finished)" : "") + (r.reading ? " (reading the rest of the log…)" : ""));
  const key = s.source.name + "|" + s.analysing + "|" + r.duration_s + "|" + s.alarm_count + "|" + (s.line ? s.line.a + s.line.b : "");
  if (key !== timelineKey && !s.analysing) { timelineKey = key; loadTimeline(); }
}

async function loadTimeline() {
  try {
    const tl = await api("GET", "/api/replay/timeline");
    const box = $("timeline");
    box.innerHTML = tl.markers.map((m) => {
      const left = 100 * m.t_s / tl.duration_s;
      const width = m.end_s === null ? 0 : 100 * (m.end_s - m.t_s) / tl.duration_s;
      return `<div class="marker ${m.kind}" data-t="${m.t_s}" style="left:${left}%;${width > 0.4 ? "width:" + width + "%" : ""}"
        title="${fmt(m.t_s, 1)} s: ${escapeHtml(m.label)}"></div>`;
    }).join("");
    box.dataset.ready = tl.ready ? "1" : "0";
  } catch (e) { timelineKey = null; }
}

$("timeline").onclick = guarded("source-error", async (ev) => {
  const m = ev.target.closest(".marker");
  if (m) await api("POST", "/api/replay/seek", { t_s: Math.max(0, parseFloat(m.dataset.t) - 2) });
});

async function refreshAlarms() {
  try {
    const list = await api("GET", "/api/alarms");
    setHtml($("alarms"), "<tr><th>start</th><th>end</th><th>evidence</th></tr>" + list.map((a) =>
      `<tr data-t="${a.start_s}"><td>${fmt(a.start_s, 1)} s</td><td>${a.end_s === null ? "active" : fmt(a.end_s, 1) + " s"}</td>` +
      `<td>${escapeHtml(a.evidence_text)}${a.explanation_text ? "<br><small>" + escapeHtml(a.explanation_text) + "</small>" : ""}</td></tr>`).join(""));
  } catch (e) { /* next time */ }
}

async function refreshPlots() {
  if (document.hidden || !last || last.source.kind === "none" && !last.vehicle.roll_deg) return;
  let p;
  try { p = await api("GET", "/api/plots?window_s=60"); } catch (e) { return; }
  const t = p.t_s, t1 = p.t_end_s, t0 = Math.max(t1 - p.window_s, t.length ? t[0] : 0), S = p.series;
  const common = { t, t0, t1, alarms: p.alarms };
  const headings = [
    { label: "attitude", color: "#1f5fd0", y: S.heading_deg, wrap: true, width: 2 },
    { label: "magnetic", color: "#d03030", y: S.mag_heading_deg, wrap: true },
    { label: "autopilot", color: "#555", y: S.ap_heading_deg, wrap: true },
    { label: "GPS course", color: "#1a9a3a", y: S.course_deg, wrap: true, dots: true },
  ];
  const unwrapped = unwrapHeadings(headings);
  drawPlot($("plot-heading"), unwrapped, Object.assign(headingRange(unwrapped), { yTicks: headingTicks }, common));
  drawPlot($("plot-field"), [{ label: "measured", color: "#8a3ab9", y: S.field_mG }],
    Object.assign({ refs: [{ label: "WMM", color: "#1a9a3a", value: p.wmm.field_mG }] }, common));
  drawPlot($("plot-incl"), [{ label: "measured", color: "#8a3ab9", y: S.inclination_deg }],
    Object.assign({ refs: [{ label: "WMM", color: "#1a9a3a", value: p.wmm.inclination_deg }] }, common));
  drawPlot($("plot-vel"), [{ label: "forward", color: "#1a9a3a", y: S.v_forward_mps },
    { label: "lateral", color: "#8a3ab9", y: S.v_lateral_mps }], common);
  drawPlot($("plot-xt"), [{ label: "cross-track", color: "#222", y: S.cross_track_m }], common);
}

// An upload is stored as upload-YYYYmmdd-HHMMSS-<its own name>: the list shows its own name (the
// stored one in the row's tooltip), so uploads do not all read "upload-2026…".
function shortName(name) {
  const m = /^upload-\d{8}-\d{6}(?:_\d+)?-(.+)$/.exec(name);
  return m ? `<span class="up">↑</span> ${escapeHtml(m[1])}` : escapeHtml(name);
}

async function loadRecordings() {
  const list = await api("GET", "/api/recordings/info");
  if (!list.some((r) => r.name === selected)) selected = list.length ? list[0].name : null;
  const tb = $("recordings").querySelector("tbody");
  const html = list.map((r) => `<tr data-name="${escapeHtml(r.name)}" class="${r.name === selected ? "selected" : ""}${r.error ? " bad" : ""}"
    title="${escapeHtml(r.error || (r.autopilot || "") + " " + r.name)}"><td>${shortName(r.name)}</td>
    <td>${r.recording ? "recording…" : (r.duration_s === null ? "—" : fmt(r.duration_s / 60, 1) + " min")}</td>
    <td>${fmtDate(r.start_unix_s)}</td><td>${fmtSize(r.size_bytes)}</td>
    <td>${escapeHtml(r.error ? "unreadable" : (r.vehicle || "—"))}</td><td>${r.compasses === null ? "—" : r.compasses}</td></tr>`).join("");
  setHtml(tb, html);                 // unchanged: leave the rows (clicks, hover) alone
  setProp($("replay"), "disabled", !selected);
}

$("recordings").onclick = (ev) => {
  const tr = ev.target.closest("tr[data-name]");
  if (!tr) return;
  selected = tr.dataset.name;
  for (const row of $("recordings").querySelectorAll("tr[data-name]")) row.classList.toggle("selected", row === tr);
  setProp($("replay"), "disabled", false);
};

function guarded(errId, fn) {
  return async (...args) => { $(errId).textContent = ""; try { await fn(...args); } catch (e) { $(errId).textContent = e.message; } };
}

$("upload").onchange = guarded("source-error", async () => {
  const file = $("upload").files[0];
  if (!file) return;
  $("upload-status").textContent = "uploading " + file.name + "…";
  try {
    const res = await fetch("/api/recordings/upload?filename=" + encodeURIComponent(file.name),
      { method: "POST", credentials: "same-origin", body: file,
        headers: { "Content-Type": "application/octet-stream", "X-MagStation-Token": await writeToken(false) } });
    const data = await res.json().catch(() => ({}));
    if (!res.ok) throw new Error(data.detail || res.statusText);
    selected = data.name;
    $("upload-status").textContent = "stored as " + data.name;
    $("upload-status").title = data.name;
    await loadRecordings();
  } catch (e) { $("upload-status").textContent = ""; throw e; } finally { $("upload").value = ""; }
});
$("replay").onclick = guarded("source-error", () => api("POST", "/api/replay/start", { recording: selected, speed: parseFloat($("speed").value) }));
$("connect-btn").onclick = guarded("source-error", () => api("POST", "/api/source", { connect: $("connect").value }));
$("stop").onclick = guarded("source-error", () => api("POST", "/api/source/stop"));
$("pause").onclick = guarded("source-error", () => api("POST", "/api/replay/pause", { paused: !(last && last.replay && last.replay.paused) }));
$("speed").onchange = guarded("source-error", () => last && last.replay ? api("POST", "/api/replay/speed", { speed: parseFloat($("speed").value) }) : null);
$("seek").oninput = () => { seeking = true; };
$("seek").onchange = guarded("source-error", async () => { try { await api("POST", "/api/replay/seek", { t_s: parseFloat($("seek").value) }); } finally { seeking = false; } });
$("alarms").onclick = guarded("source-error", async (ev) => {
  const tr = ev.target.closest("tr[data-t]");
  if (tr && last && last.replay) await api("POST", "/api/replay/seek", { t_s: Math.max(0, parseFloat(tr.dataset.t) - 2) });
});
$("line-set").onclick = guarded("line-error", () => api("PUT", "/api/line", {
  a: [parseFloat($("a-lat").value), parseFloat($("a-lon").value)], b: [parseFloat($("b-lat").value), parseFloat($("b-lon").value)] }));
$("line-mission").onclick = guarded("line-error", () => api("POST", "/api/line/from-mission"));
$("line-clear").onclick = guarded("line-error", () => api("DELETE", "/api/line"));
for (const id of ["dl-log", "dl-json", "dl-csv"]) $(id).onclick = (ev) => { if ($(id).classList.contains("disabled")) ev.preventDefault(); };

// ---- Calibration in use: where the station's calibration comes from, per vehicle/airframe (self-contained).
let inUseKey = null, choiceTouched = false;   // touched: the operator picked an option not yet used
$("cal-choice").onchange = () => { choiceTouched = true; };
async function loadInUseOptions() {
  const d = await api("GET", "/api/calibration/in-use");
  const sel = $("cal-choice"), keep = choiceTouched ? sel.value : null;
  sel.innerHTML = d.options.map((o) => `<option value="${escapeHtml(o.source + (o.name ? ":" + o.name : ""))}">` +
    `${escapeHtml(o.label)}</option>`).join("");
  const cur = d.current.source + (d.current.source === "recording" ? ":" + d.current.label.replace(/^the dance in /, "") : "");
  sel.value = [...sel.options].some((o) => o.value === keep) ? keep : cur;
}
function renderInUse(s) {
  const c = s.calibration_choice;
  if (!c) return;
  setText($("cal-in-use"), c.source === "none" ? "none: the field as the autopilot sent it" +
    (c.airframe ? " (" + c.airframe + ")" : "") : c.label + " — " + c.frame + (c.note ? "; " + c.note : "") +
    " [" + c.source + (c.airframe ? ", " + c.airframe : "") + "]" + (c.applied ? ". " + c.applied : ""));
  setProp($("cal-in-use").dataset, "source", c.source);
  const key = s.source.name + "|" + c.source + "|" + c.label + "|" + (s.wizard && s.wizard.state);
  if (key !== inUseKey) { inUseKey = key; loadInUseOptions().catch(() => { inUseKey = null; }); }
}
$("cal-use").onclick = guarded("cal-error", async () => {
  const v = $("cal-choice").value, i = v.indexOf(":");
  const body = i < 0 ? { source: v } : { source: v.slice(0, i), name: v.slice(i + 1) };
  choiceTouched = false;
  $("cal-in-use").textContent = "fitting / applying…";
  await api("POST", "/api/calibration/in-use", body);
});
$("cal-upload").onchange = guarded("cal-error", async () => {
  const file = $("cal-upload").files[0];
  if (!file) return;
  try {
    const res = await fetch("/api/calibration/in-use/upload?filename=" + encodeURIComponent(file.name),
      { method: "POST", credentials: "same-origin", body: file,
        headers: { "Content-Type": "application/octet-stream", "X-MagStation-Token": await writeToken(false) } });
    const data = await res.json().catch(() => ({}));
    if (!res.ok) throw new Error(data.detail || res.statusText);
  } finally { $("cal-upload").value = ""; }
});
// ---- end of the calibration-in-use block

connectState(render, (up) => { if (!up) $("status").textContent = "station connection lost, retrying…"; });
setupViewer("viewer");
loadRecordings().catch((e) => { $("source-error").textContent = e.message; });
setInterval(refreshAlarms, 1000);
setInterval(refreshPlots, 500);
setInterval(() => loadRecordings().catch(() => {}), 5000);
