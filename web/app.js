// Station overview page.
"use strict";
const $ = (id) => document.getElementById(id);
let last = null, seeking = false;

function render(s) {
  last = s;
  $("status").textContent = linkText(s);
  const b = $("alarm-banner");
  if (s.alarm.active) {
    b.className = "banner alarm";
    b.textContent = "MAGNETIC INTERFERENCE ALARM" + (s.alarm.evidence.length ? ": " + s.alarm.evidence.join(", ") : "") +
      (s.alarm.since_s !== null ? " (since " + fmt(s.alarm.since_s, 1) + " s)" : "");
  } else { b.className = "banner ok"; b.textContent = "No interference alarm"; }
  const v = s.vehicle;
  $("v-rp").textContent = fmt(v.roll_deg, 1, "°") + " / " + fmt(v.pitch_deg, 1, "°");
  $("v-hdg").textContent = fmt(v.heading_att_deg, 1, "°") + " / " + fmt(v.heading_mag_deg, 1, "°");
  $("v-aphdg").textContent = v.ap_yaw_deg === null ? "—" : fmt(((v.ap_yaw_deg % 360) + 360) % 360, 1, "°");
  $("v-vel").textContent = fmt(v.v_forward_mps, 2, " m/s") + " / " + fmt(v.v_lateral_mps, 2, " m/s");
  $("v-xt").textContent = fmt(v.cross_track_m, 2, " m");
  $("v-field").textContent = fmt(v.field_mG, 0, " mG");
  $("v-cal").textContent = s.calibration_in_use ? "in use" : "none: headings from the uncorrected field";
  $("v-pos").textContent = v.lat_deg === null ? "—" : fmt(v.lat_deg, 6) + ", " + fmt(v.lon_deg, 6) + " / fix " + v.fix_type;
  const r = s.replay;
  $("replay-controls").hidden = !r;
  if (r) {
    $("pause").textContent = r.paused ? "Resume" : "Pause";
    $("seek").max = r.duration_s;
    if (!seeking) $("seek").value = r.t_s;
    $("replay-time").textContent = fmt(r.t_s, 1) + " / " + fmt(r.duration_s, 1) + " s ×" + r.speed + (r.finished ? " (finished)" : "");
  }
  $("line-text").textContent = s.line ? "A " + s.line.a.map((x) => x.toFixed(6)).join(", ") + " → B " +
    s.line.b.map((x) => x.toFixed(6)).join(", ") + " (" + s.line.source + ")" : "none";
  $("alarm-count").textContent = s.alarm_count;
  $("events").innerHTML = s.events.slice().reverse().map((e) =>
    `<div class="${e.level}">${fmt(e.t_s, 1)} s  ${escapeHtml(e.text)}</div>`).join("");
}

async function refreshAlarms() {
  try {
    const list = await api("GET", "/api/alarms");
    $("alarms").innerHTML = "<tr><th>start</th><th>end</th><th>evidence</th></tr>" + list.map((a) =>
      `<tr><td>${fmt(a.start_s, 1)} s</td><td>${a.end_s === null ? "active" : fmt(a.end_s, 1) + " s"}</td><td>${escapeHtml(a.evidence.join(", "))}</td></tr>`).join("");
  } catch (e) { /* next time */ }
}

async function loadRecordings() {
  const names = await api("GET", "/api/recordings");
  $("recording").innerHTML = names.map((n) => `<option>${escapeHtml(n)}</option>`).join("");
}

function guarded(errId, fn) {
  return async () => { $(errId).textContent = ""; try { await fn(); } catch (e) { $(errId).textContent = e.message; } };
}

$("replay").onclick = guarded("source-error", () => api("POST", "/api/replay/start", { recording: $("recording").value, speed: parseFloat($("speed").value) }));
$("connect-btn").onclick = guarded("source-error", () => api("POST", "/api/source", { connect: $("connect").value }));
$("stop").onclick = guarded("source-error", () => api("POST", "/api/source/stop"));
$("pause").onclick = guarded("source-error", () => api("POST", "/api/replay/pause", { paused: !(last && last.replay && last.replay.paused) }));
$("speed").onchange = guarded("source-error", () => last && last.replay ? api("POST", "/api/replay/speed", { speed: parseFloat($("speed").value) }) : null);
$("seek").oninput = () => { seeking = true; };
$("seek").onchange = guarded("source-error", async () => { seeking = false; await api("POST", "/api/replay/seek", { t_s: parseFloat($("seek").value) }); });
$("line-set").onclick = guarded("line-error", () => api("PUT", "/api/line", {
  a: [parseFloat($("a-lat").value), parseFloat($("a-lon").value)], b: [parseFloat($("b-lat").value), parseFloat($("b-lon").value)] }));
$("line-mission").onclick = guarded("line-error", () => api("POST", "/api/line/from-mission"));

connectState(render, (up) => { if (!up) $("status").textContent = "station connection lost, retrying…"; });
setupViewer("viewer", "initialCameraPosition=3,1.5,9&initialCameraLookAt=8.5,1.5,0");
loadRecordings();
setInterval(refreshAlarms, 1000);
