// Fleet page: the compass history (GET /api/fleet/*), read-only; a replay button per flight.
"use strict";

const $ = (id) => document.getElementById(id);

function table(el, head, rows) {
  el.innerHTML = "<tr>" + head.map((h) => "<th>" + escapeHtml(h) + "</th>").join("") + "</tr>" + rows.join("");
}

function cells(values) { return values.map((v) => "<td>" + v + "</td>").join(""); }

function date(unix) { return unix ? new Date(unix * 1000).toISOString().slice(0, 10) : "—"; }

function replayButton(name) {
  return "<button data-replay=\"" + escapeHtml(name) + "\">replay</button>";
}

async function startReplay(name) {
  $("replay-error").textContent = "";
  try {
    await api("POST", "/api/replay/start", { recording: name, speed: 1 });
    location.href = "index.html";
  } catch (e) {
    $("replay-card").hidden = false;
    $("replay-text").textContent = name;
    $("replay-error").textContent = e.message;
  }
}

function showReplayOffer() {
  const name = new URLSearchParams(location.search).get("replay");
  if (!name) return;
  $("replay-card").hidden = false;
  $("replay-text").textContent = "Replay " + name + " in the station?";
  $("replay-go").onclick = () => startReplay(name);   // a click, never on page load
}

// drawn in the chart's own pixels (a stretched viewBox widened the text and the dots), again on resize
let shownHistory = null;
window.addEventListener("resize", () => { if (shownHistory) drawHistory(shownHistory); });
function drawHistory(h) {
  shownHistory = h;
  const svg = $("chart"), W = Math.max(300, Math.round(svg.getBoundingClientRect().width) || 900), H = 260, pad = 36;
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  // the first compass (the drift alert names any other)
  const flights = h.flights.filter((f) => !f.compass && f.start_unix_s && f.fit_ofs_x_mG !== null);
  if (!flights.length) { svg.innerHTML = "<text x='20' y='30'>no fitted flights</text>"; return; }
  // the site's apparent offset (a local field) removed, as the drift test does
  const ofs = flights.map((f) => [f.fit_ofs_x_mG - (f.site_offset_x_mG || 0), f.fit_ofs_y_mG - (f.site_offset_y_mG || 0),
    f.fit_ofs_z_mG - (f.site_offset_z_mG || 0)]);
  const ref = [0, 1, 2].map((k) => { const v = ofs.slice(0, 5).map((o) => o[k]).sort((a, b) => a - b); return v[Math.floor(v.length / 2)]; });
  const drift = ofs.map((o) => Math.hypot(o[0] - ref[0], o[1] - ref[1], o[2] - ref[2]));
  const t = flights.map((f) => f.start_unix_s), t0 = Math.min(...t), t1 = Math.max(...t) + 1;
  const dmax = Math.max(20, ...drift), imax = Math.max(10, ...flights.map((f) => f.interference_pct || 0));
  const x = (v) => pad + (v - t0) / (t1 - t0) * (W - 2 * pad);
  const y = (v, m) => H - pad - v / m * (H - 2 * pad);
  let s = "<line x1='" + pad + "' y1='" + (H - pad) + "' x2='" + (W - pad) + "' y2='" + (H - pad) + "' stroke='#888'/>";
  s += "<text x='4' y='" + (pad - 8) + "' font-size='11'>" + dmax.toFixed(0) + " mG</text>";
  s += "<text x='" + (W - pad - 30) + "' y='" + (pad - 8) + "' font-size='11'>" + imax.toFixed(0) + " %</text>";
  s += "<text x='" + pad + "' y='" + (H - 8) + "' font-size='11'>" + date(t0) + "</text><text x='" + (W - pad - 70) + "' y='" + (H - 8) + "' font-size='11'>" + date(t1) + "</text>";
  for (const c of h.calibrations) s += "<line x1='" + x(c.unix_s) + "' x2='" + x(c.unix_s) + "' y1='" + pad + "' y2='" + (H - pad) + "' stroke='#1a7f37' stroke-dasharray='4'/>";
  s += "<polyline fill='none' stroke='#1565c0' stroke-width='2' points='" + drift.map((d, i) => x(t[i]) + "," + y(d, dmax)).join(" ") + "'/>";
  flights.forEach((f, i) => {
    if (f.interference_pct !== null) s += "<circle r='3' cx='" + x(t[i]) + "' cy='" + y(f.interference_pct, imax) + "' fill='" + (f.alarm_count ? "#c00" : "#888") + "'/>";
  });
  svg.innerHTML = s;
}

async function showAirframe(name) {
  $("history-title").textContent = "Airframe history: " + name;
  try { drawHistory(await api("GET", "/api/fleet/airframes/" + encodeURIComponent(name))); }
  catch (e) { $("error").textContent = e.message; }
}

function renderSummary(s) {
  $("history").textContent = "history " + s.history + ": " + s.flights + " logs, " + s.failed + " failed";
  const important = s.alerts.filter((a) => a.kind !== "interference");
  const interference = s.alerts.length - important.length;
  $("summary").textContent = important.length + " fleet alerts, " + interference + " flights with interference alarms";
  table($("alerts"), ["kind", "airframe / site", "date", "finding"], important.map((a) => "<tr>" + cells([
    "<span class='kind-" + escapeHtml(a.kind) + "'>" + escapeHtml(a.kind) + "</span>", escapeHtml(a.airframe || a.site || ""),
    date(a.unix_s), escapeHtml(a.message)]) + "</tr>"));
  table($("airframes"), ["airframe", "flights", "failed", "last flight", "alarms", "interference %", "offset change mG"],
    s.airframes.map((a) => "<tr class='pick' data-airframe=\"" + escapeHtml(a.airframe) + "\">" + cells([
      escapeHtml(a.airframe), a.flights, a.failed || 0, date(a.last_unix_s), a.alarms, fmt(a.mean_interference_pct, 1),
      fmt(a.latest_ofs_change_mG, 1)]) + "</tr>"));
  table($("sites"), ["site", "flights", "airframes", "field vs WMM", "inclination vs WMM", ""],
    s.sites.map((x) => "<tr>" + cells([escapeHtml(x.name), x.flights, x.airframes.length, fmt(x.strength_effect_mG, 0, " mG"),
      fmt(x.inclination_effect_deg, 1, "°"), x.anomaly ? "<span class='error'>anomaly</span>" : ""]) + "</tr>"));
}

function renderWorst(rows) {
  table($("worst"), ["date", "airframe", "log", "site", "alarms", "evidence", "heading vs autopilot p99", "cross-track", ""],
    rows.map((r) => "<tr>" + cells([date(r.start_unix_s), escapeHtml(r.airframe), escapeHtml(r.file_name), escapeHtml(r.site || ""),
      r.alarm_count, escapeHtml(r.alarm_evidence || ""), fmt(r.heading_vs_autopilot_max_deg, 1, "°"),
      fmt(r.max_cross_track_m, 2, " m"), replayButton(r.file_name)]) + "</tr>"));
}

document.addEventListener("click", (ev) => {
  const b = ev.target.closest("[data-replay]");
  if (b) { startReplay(b.dataset.replay); return; }
  const r = ev.target.closest("[data-airframe]");
  if (r) showAirframe(r.dataset.airframe);
});

(async function main() {
  showReplayOffer();
  try {
    const s = await api("GET", "/api/fleet/summary");
    renderSummary(s);
    renderWorst(await api("GET", "/api/fleet/flights?limit=30"));
    const drift = s.alerts.find((a) => a.kind === "offset_drift");
    if (drift) showAirframe(drift.airframe); else if (s.airframes.length) showAirframe(s.airframes[0].airframe);
  } catch (e) { $("error").textContent = e.message; }
})();
