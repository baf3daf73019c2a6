// Guided three-axis calibration (seed 004 handheld procedure): X, Y, Z full turns, then tumble.
"use strict";
const $ = (id) => document.getElementById(id);
const ORDER = ["x", "y", "z", "tumble", "done"];

function vec(v, d = 1) { return v ? "[" + v.map((x) => fmt(x, d)).join(", ") + "]" : "—"; }
function mat(m) { return m ? m.map((r) => vec(r, 4)).join("<br>") : "—"; }

function render(s) {
  $("status").textContent = linkText(s);
  const w = s.wizard;
  $("instruction").textContent = w.instruction;
  $("start").disabled = w.state === "running";
  $("finish").disabled = w.state !== "running";
  const cur = ORDER.indexOf(w.step);
  document.querySelectorAll("#steps li").forEach((li) => {
    const step = li.dataset.step, i = ORDER.indexOf(step);
    li.className = w.state === "idle" ? "" : (i < cur ? "done" : (i === cur ? "current" : ""));
    const bar = li.querySelector(".bar"), deg = li.querySelector(".deg");
    if (!bar) return;
    let frac, text;
    if (step === "tumble") {
      frac = w.coverage / w.coverage_target;
      text = "sphere coverage " + fmt(100 * w.coverage, 0) + " % (target " + fmt(100 * w.coverage_target, 0) + " %)";
    } else {
      const d = w.progress_deg[step];
      frac = d / w.turn_target_deg;
      text = fmt(Math.min(d, 9999), 0) + "° of " + fmt(w.turn_target_deg, 0) + "°";
    }
    bar.className = "bar" + (frac >= 1 ? " done" : "");
    bar.firstElementChild.style.width = Math.min(100, 100 * frac) + "%";
    deg.textContent = text;
  });
  $("live-fit").textContent = w.state === "idle" ? "" : w.samples + " samples" +
    (w.rls_offsets_mG ? " · live fit offsets " + vec(w.rls_offsets_mG, 0) + " mG, field " + fmt(w.rls_field_mG, 0) + " mG" : "") +
    (w.expected_field_mG ? " · WMM " + fmt(w.expected_field_mG, 0) + " mG" : "");
  $("warnings").innerHTML = w.warnings.map((t) => `<div>⚠ ${escapeHtml(t)}</div>`).join("");
  const r = w.result;
  $("result-card").hidden = !r;
  if (r) {
    $("result-status").textContent = r.status;
    $("result-status").className = r.status === "ok" ? "good" : "error";
    $("result-message").textContent = r.message || "";
    const rows = [
      ["Samples", r.samples],
      ["Offsets (mG)", vec(r.offsets_mG)],
      ["Matrix C", mat(r.matrix)],
      ["Residual RMS", fmt(r.residual_rms_mG, 2, " mG")],
      ["Coverage", fmt(100 * (r.coverage || 0), 0, " %")],
      ["Fitted field / WMM", fmt(r.field_strength_mG, 0, " mG") + " / " + fmt(r.expected_field_mG, 0, " mG")],
      ["Misalignment (deg)", vec(r.misalignment_deg, 2)],
      ["Heading error (est.)", fmt(r.heading_error_deg, 2, "°")],
    ];
    $("result-table").innerHTML = rows.map(([k, v]) => `<tr><td>${k}</td><td>${v}</td></tr>`).join("");
    $("accept").disabled = r.status !== "ok" || w.state === "accepted";
    $("export").disabled = r.status !== "ok";
  }
  const pw = w.param_write;
  $("param-write").innerHTML = !pw ? "" : `<div class="${pw.state === "failed" ? "error" : (pw.state === "written" ? "good" : "muted")}">` +
    escapeHtml(pw.message) + (pw.state === "writing" ? ` (${pw.confirmed.length}/${pw.total} confirmed)` : "") + "</div>" +
    (pw.failed.length ? `<div class="error">Did not stick: ${escapeHtml(pw.failed.join(", "))}</div>` : "");
}

function guarded(fn) {
  return async () => { $("cal-error").textContent = ""; try { await fn(); } catch (e) { $("cal-error").textContent = e.message; } };
}
$("start").onclick = guarded(() => api("POST", "/api/calibration/start"));
$("finish").onclick = guarded(() => api("POST", "/api/calibration/finish"));
$("reset").onclick = guarded(() => api("POST", "/api/calibration/reset"));
$("redo").onclick = guarded(async () => { await api("POST", "/api/calibration/reset"); await api("POST", "/api/calibration/start"); });
$("accept").onclick = guarded(() => api("POST", "/api/calibration/accept"));
$("export").onclick = () => {
  const ap = $("export-ap").value;
  location.href = "/api/calibration/params" + (ap ? "?autopilot=" + ap : "");
};

connectState(render, (up) => { if (!up) $("status").textContent = "station connection lost, retrying…"; });
setupViewer("viewer", "initialCameraPosition=-4.8,1.7,4.2&initialCameraLookAt=0,1.7,1.2");
