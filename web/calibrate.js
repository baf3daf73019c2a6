// Compass calibration page: guided dance (every compass), the vehicle's own calibrator, large-vehicle
// fixed-yaw, then write, reboot, heading check.  Everything shown comes from the state pushed on /ws.
"use strict";
const $ = (id) => document.getElementById(id);
const ORDER = ["x", "y", "z", "tumble", "done"];
let last = null, sectionCentres = null, rebootAsked = false;
let modeChosen = false;        // the operator picked a mode after a run: the radios are theirs until the next run
let discardAsked = null;       // "start" | "reset" | "redo" waiting for the operator's yes

function vec(v, d = 1) { return v ? "[" + v.map((x) => fmt(x, d)).join(", ") + "]" : "—"; }
function show(id, on) { setProp($(id), "hidden", !on); }
function pct(f) { return Math.floor(100 * (f || 0)) + " %"; }     // floored: never shows a target reached early
function cap(s) { return s ? s[0].toUpperCase() + s.slice(1) : s; }

// What Start/Reset would throw away (null: nothing worth asking about).
function wouldLose(w) {
  const pw = w.param_write;
  if (pw && pw.state === "written" || w.reboot || w.heading_check)
    return "The calibration is written to the vehicle (it keeps it); this page forgets the result" +
      (w.reboot ? ", the reboot" : "") + (w.heading_check ? ", the heading check" : "") + ".";
  if (w.result && w.result.status === "ok") return "The result is not written to the vehicle: it is lost (Export parameters keeps a copy).";
  return null;
}

function renderControl(w) {
  const running = w.state === "running";
  if (running) modeChosen = false;
  document.querySelectorAll("#modes input").forEach((r) => {
    setProp(r, "disabled", running);
    if (w.state !== "idle" && !modeChosen) setProp(r, "checked", r.value === w.mode);
  });
  const again = w.state !== "idle" && !running;
  setText($("start"), again ? "Start over" : "Start");
  $("start").classList.toggle("primary", w.state === "idle");      // one primary action at a time
  const lose = discardAsked ? wouldLose(w) : null;
  if (discardAsked && !lose) discardAsked = null;
  show("discard-confirm", !!lose);
  setText($("discard-text"), lose ? lose + " " + ({ start: "Start over?", redo: "Redo?", reset: "Reset?" }[discardAsked]) : "");
  setText($("instruction"), w.instruction);
  const hc = w.heading_check && w.heading_check.result;
  $("instruction").classList.toggle("failed", !!hc && hc.verdict === "fail");
  const b = w.banner;
  show("banner", !!b);
  if (b) { setProp($("banner"), "className", "cal-banner " + b.level); setText($("banner"), b.text); }
  show("hint", !!w.hint);
  setText($("hint"), w.hint || "");
  setHtml($("warnings"), w.warnings.map((t) => `<div>⚠ ${escapeHtml(t)}</div>`).join(""));
  setProp($("start"), "disabled", w.state === "running");
  setProp($("finish"), "disabled", w.state !== "running" || w.mode === "fixed_yaw");
  const primary = w.compasses.find((c) => c.index === 0);
  // the field: fitted (a result), live (a trusted running fit) or preliminary (an early one)
  const fitted = w.result && w.result.status === "ok" && w.result.field_strength_mG;
  const fieldText = fitted ? " · fitted field " + fmt(w.result.field_strength_mG, 0) + " mG" :
    (w.live_field_mG ? (primary && primary.trusted ? " · live field " : " · preliminary field ") + fmt(w.live_field_mG, 0) + " mG" : "");
  setText($("live-fit"), w.state === "idle" || w.mode === "fixed_yaw" ? "" : w.samples + " samples" + fieldText +
    (w.expected_field_mG ? " · WMM " + fmt(w.expected_field_mG, 0) + " mG" : ""));
  renderWrite(w.param_write);
}

function renderWrite(pw) {
  if (!pw) { setHtml($("param-write"), ""); return; }
  const bad = pw.state === "failed" || pw.state === "refused";
  const cls = bad ? "error" : (pw.state === "written" ? "good" : "muted");
  let html = `<div class="write ${cls}">${pw.state === "written" ? "✔ " : (bad ? "✖ " : "")}${escapeHtml(pw.message)}` +
    (pw.state === "writing" && pw.total ? ` (${pw.confirmed.length}/${pw.total} confirmed)` : "") + "</div>";
  const fails = pw.failures || [];
  if (fails.length) {
    html += "<ul class='failures'>" + fails.slice(0, 3).map((f) => `<li>${escapeHtml(f.text)}</li>`).join("") +
      (fails.length > 3 ? `<li>… and ${fails.length - 3} more</li>` : "") + "</ul>";
  }
  setHtml($("param-write"), html);
}

function renderSteps(w) {
  // the vehicle's calibrator keeps its own count (its card and the blue sections): our X/Y/Z steps
  // beside its instruction would contradict it
  show("steps-card", w.mode === "guided" && (w.state === "running" || w.state === "idle"));
  const cur = ORDER.indexOf(w.step);
  const target = w.turn_target_deg - w.settings.turn_tolerance_deg;
  document.querySelectorAll("#steps li").forEach((li) => {
    const step = li.dataset.step, i = ORDER.indexOf(step);
    setProp(li, "className", w.state === "idle" || w.waiting_for ? "" : (i < cur ? "done" : (i === cur ? (w.paused ? "current paused" : "current") : "")));
    const bar = li.querySelector(".bar"), deg = li.querySelector(".deg");
    if (!bar) return;
    let frac, text;
    if (step === "tumble") {
      frac = w.coverage / w.coverage_target;
      text = "sphere " + pct(w.coverage) + " seen (the step needs " + pct(w.coverage_target) + ")";
    } else {
      const d = w.progress_deg[step];
      frac = d / target;
      text = frac >= 1 ? "✓ full turn (" + fmt(d, 0) + "°, within " + fmt(w.settings.turn_tolerance_deg, 0) + "° of 360°)" :
        fmt(d, 0) + "° of " + fmt(w.turn_target_deg, 0) + "°";
    }
    setProp(bar, "className", "bar" + (frac >= 1 ? " done" : ""));
    setProp(bar.firstElementChild.style, "width", Math.min(100, 100 * frac) + "%");
    setText(deg, text);
  });
  const p = w.next_pose;
  show("next-pose", !!p);
  if (p) setText($("next-pose"), "That pose fills " + p.fills + " of the " + p.missing +
    " directions still missing (grey on the sphere).");
}

function compassRow(c, w) {
  const r = c.result;
  const inc = `<input type="checkbox" data-compass="${c.index}" ${c.included ? "checked" : ""} title="include in the result">`;
  if (!r) {
    return `<tr><td>${inc}</td><td>${c.index + 1}</td><td>${c.samples}</td><td>${c.coverage === null ? "—" : pct(c.coverage)}</td>` +
      `<td colspan="3" class="muted">${!c.live_field_mG ? "collecting…" : (c.trusted ? "live field " + fmt(c.live_field_mG, 0) + " mG" :
        "preliminary fit " + fmt(c.live_field_mG, 0) + " mG (settles with more turns)")}</td></tr>`;
  }
  const pass = r.pass ? `<span class="good">pass</span>` : `<span class="error">fail</span>`;
  const o = r.orientation;
  const orient = !o ? "—" : (o.status === "rotation_found" ? `<b>${o.detected_name}</b> (was ${o.current})` :
    (o.status === "confirmed" ? o.detected_name + " ✓" : o.status));
  let row = `<tr class="${c.included ? "" : "left-out"}"><td>${inc}</td><td>${c.index + 1}</td><td>${pass}</td>` +
    `<td title="RMS residual about the fitted sphere, and the threshold">${fmt(r.fitness_mG, 1)} ≤ ${fmt(r.fitness_threshold_mG, 0)}</td>` +
    `<td title="predicted worst-case heading error">±${fmt(r.heading_error_deg, 1)}°</td><td>${orient}</td>` +
    `<td>${fmt(r.field_strength_mG, 0)} mG</td></tr>`;
  const notes = (r.reasons || []).map((t) => `<div class="error">${escapeHtml(t)}</div>`)
    .concat((r.cautions || []).map((t) => `<div class="warn">${escapeHtml(t)}</div>`));
  if (notes.length) row += `<tr class="notes"><td></td><td colspan="6">${notes.join("")}</td></tr>`;
  return row;
}

function renderCompasses(w) {
  show("compass-card", w.compasses.length > 0 && w.mode !== "fixed_yaw");
  if (!w.compasses.length) return;
  // during the dance the steps fill the left column: the compasses go under the sphere (at
  // 1280x720 they were cut off below the steps), and back beside the result once it is in
  const running = w.state === "running" && w.mode === "guided", card = $("compass-card");
  const home = running ? $("panel-mid") : $("panel-left");
  if (card.parentElement !== home) home.insertBefore(card, running ? $("onboard-card") : null);
  const done = w.compasses.some((c) => c.result);
  const head = done ? "<tr><th>Use</th><th>#</th><th>Result</th><th>Fitness mG</th><th>Heading</th><th>Orientation</th><th>Field</th></tr>" :
    "<tr><th>Use</th><th>#</th><th>Samples</th><th title='directions of this compass&#39;s own corrected field (its live fit); the sphere counts the directions from the attitude'>Own coverage</th><th colspan='3'></th></tr>";
  setHtml($("compass-table"), head + w.compasses.map((c) => compassRow(c, w)).join(""));
  $("fitness").value = w.fitness_level;
  const k = w.consistency;
  const limits = w.compasses.filter((c) => c.result && c.result.fitness_threshold_mG).map((c) => c.result.fitness_threshold_mG);
  const note = done && limits.length > 1 && Math.max(...limits) > Math.min(...limits) ?
    `<div class="muted">Fitness limits: compass 1 ≤ ${fmt(Math.min(...limits), 0)} mG (the level chosen), the others ≤ ` +
    `${fmt(Math.max(...limits), 0)} mG: ArduPilot doubles the limit for non-primary compasses.</div>` : "";
  setHtml($("consistency"), note + (k ? `<div class="${k.status === "ok" ? "good" : "error"}">${escapeHtml(k.text)}</div>` : ""));
}

function renderCoverage(w) {
  show("coverage-card", w.mode !== "fixed_yaw" || w.state === "idle");
  const ob = w.onboard;
  let sections = null;
  if (ob && ob.compasses.length && sectionCentres) sections = ob.compasses[0].sections || [];
  setText($("coverage-text"), w.state === "idle" ? "" : pct(w.coverage) + " of the sphere, from the attitude" +
    (sections ? " · vehicle's calibrator: " + sections.length + " of 80 sections (blue)" : ""));
  drawSphere($("sphere"), w.coverage_cells, w.current_direction, sections, sectionCentres);
}

function renderOnboard(w) {
  const ob = w.onboard;
  show("onboard-card", !!ob);
  if (!ob) return;
  const rows = ["<tr><th>Compass</th><th>Vehicle</th><th>Offsets vehicle / ours (mG)</th><th>Fitness vehicle / ours</th></tr>"];
  ob.compasses.forEach((c) => {
    const r = c.report, cmp = c.compare;
    const st = r ? (r.success ? "<span class='good'>success</span>" : "<span class='error'>" + escapeHtml(c.status_text) + "</span>") :
      escapeHtml(c.status_text) + " " + (c.completion_pct || 0) + " %";
    rows.push(`<tr><td>${c.index + 1}</td><td>${st}</td><td>${r ? vec(r.ofs_mG, 0) : "—"}${cmp ? "<br>" + vec(cmp.our_ofs_mG, 0) : ""}</td>` +
      `<td>${r ? fmt(r.fitness_mG, 1) : "—"} / ${cmp ? fmt(cmp.our_fitness_mG, 1) : "—"} mG</td></tr>`);
  });
  setHtml($("onboard-table"), rows.join("") + `<tr><td colspan="4" class="muted small">${escapeHtml(ob.message)}</td></tr>`);
  setProp($("ob-accept"), "disabled", ob.state !== "reported");
  setProp($("ob-cancel"), "disabled", !["starting", "running", "reported"].includes(ob.state));
}

function renderResult(w, vehicleAutopilot) {
  const r = w.result;
  show("result-card", !!r);
  if (!r) return;
  setText($("result-status"), r.status);
  setProp($("result-status"), "className", r.status === "ok" ? "good" : "error");
  setText($("result-message"), r.status === "ok" ? (r.consistency_warning || "") : (r.message || ""));
  const px4 = (vehicleAutopilot || w.result.autopilot || "ardupilot") === "px4";
  const rows = [`<tr><th>#</th><th>Offsets b (mG)</th><th>${px4 ? "CAL_MAGn_x/y/zOFF (G)" : "COMPASS_OFSn_X/Y/Z"}</th>` +
    `<th>${px4 ? "CAL_MAGn_ROT" : "ORIENTn"}</th><th>Own coverage</th></tr>`];
  w.compasses.filter((c) => c.included && c.result && c.result.status === "ok").forEach((c) => {
    const res = c.result, ap = px4 ? res.px4_params : res.ardupilot_params, k = c.index;
    const n = k ? String(k + 1) : "";
    const ofs = px4 ? ["X", "Y", "Z"].map((a) => ap[`CAL_MAG${k}_${a}OFF`]) : ["X", "Y", "Z"].map((a) => ap[`COMPASS_OFS${n}_${a}`]);
    const rot = px4 ? ap[`CAL_MAG${k}_ROT`] : ap[`COMPASS_ORIENT${n}`];
    const o = res.orientation;
    rows.push(`<tr><td>${k + 1}</td><td>${vec(res.offsets_mG, 1)}</td><td>${vec(ofs, px4 ? 4 : 1)}</td>` +
      `<td>${rot === undefined ? "unchanged" : fmt(rot, 0) + (o && o.detected_name ? " " + o.detected_name : "")}</td>` +
      `<td title="directions of this compass's own corrected field in the final fit (it needs 25 %); the sphere counts them from the attitude">${pct(res.coverage)}</td></tr>`);
  });
  setHtml($("result-table"), rows.join(""));
  const pw = w.param_write;
  setProp($("accept"), "disabled", r.status !== "ok" || (pw && ["checking", "writing", "written"].includes(pw.state)));
  setText($("accept"), pw && pw.state === "failed" ? "Retry the write" : "Accept and write");
  setProp($("export"), "disabled", r.status !== "ok");
  const obAcceptable = w.onboard && w.onboard.state === "reported";     // one primary action at a time
  $("accept").classList.toggle("primary", !$("accept").disabled && !obAcceptable);
}

function renderAfter(w) {
  const pw = w.param_write, rb = w.reboot, hc = w.heading_check;
  const fixedDone = w.fixed_yaw && w.fixed_yaw.state === "done";
  const on = (!!(pw && pw.state === "written") || !!rb || !!hc || fixedDone) && (w.mode !== "fixed_yaw" || fixedDone);
  show("after-card", on);
  if (!on) return;
  const waiting = rb && ["sent", "waiting"].includes(rb.state);
  setProp($("reboot"), "disabled", waiting);
  show("reboot-confirm", rebootAsked && !waiting);
  setText($("reboot-text"), rb ? rb.message : "");
  const measuring = hc && hc.state === "measuring";
  setProp($("hc-measure"), "disabled", measuring || waiting);
  setProp($("hc-walk"), "disabled", measuring || waiting);
  setProp($("hc-walk-stop"), "disabled", !(measuring && hc.kind === "walk"));
  let html = "";
  if (hc && hc.result) {
    const r = hc.result;
    html = `<div class="${r.verdict === "pass" ? "good" : "error"}">${r.verdict === "fail" ? "✖ too far off: " : ""}${escapeHtml(r.message || "")}</div>` +
      (r.ok ? `<div class="muted small">compass ${fmt(r.heading_deg, 1)}° ± ${fmt(r.spread_deg, 1)}° over ${r.samples} samples` +
        (r.distance_m ? `, walk ${fmt(r.distance_m, 1)} m (max ${fmt(r.off_line_m, 1)} m off the line)` : "") + "</div>" : "");
  } else if (measuring) html = `<div class="muted">measuring… ${hc.samples} samples${hc.kind === "walk" ? ", " + fmt(hc.distance_m, 1) + " m" : ""}</div>`;
  setHtml($("hc-result"), html);
}

function renderFixed(w) {
  show("fixed-card", w.mode === "fixed_yaw" && w.state !== "idle");
  if (w.mode !== "fixed_yaw") return;
  const fy = w.fixed_yaw, hc = w.heading_check;
  const walking = hc && hc.state === "measuring";
  setProp($("fy-walk"), "disabled", walking); setProp($("fy-walk-stop"), "disabled", !walking);
  setProp($("fy-gps"), "disabled", !(hc && hc.result && hc.result.reference_deg !== undefined));
  setText($("fy-walk-text"), hc ? (walking ? "walking… " + fmt(hc.distance_m, 1) + " m" :
    (hc.result && hc.result.reference_deg !== undefined ? "GPS course " + fmt(hc.result.reference_deg, 1) + "° over " + fmt(hc.result.distance_m, 1) + " m" :
      (hc.result ? hc.result.message : ""))) : "");
  if (!fy) { setHtml($("fy-table"), ""); return; }
  const rows = ["<tr><th>Compass</th><th>Vehicle's new COMPASS_OFS</th><th>Ours (same formula)</th></tr>"];
  Object.keys(fy.ours_ofs_mG).forEach((k) => rows.push(`<tr><td>${+k + 1}</td><td>${vec(fy.vehicle_ofs_mG[k], 1)}</td><td>${vec(fy.ours_ofs_mG[k], 1)}</td></tr>`));
  const c = fy.check;
  if (c) {
    rows.push(`<tr><td colspan="3" class="${c.ok ? "good" : "warn"}">Check against the WMM: heading ${fmt(c.heading_deg, 1)}° ` +
      `(${c.heading_error_deg > 0 ? "+" : ""}${fmt(c.heading_error_deg, 1)}° from ${fmt(fy.yaw_deg, 1)}°), field ${fmt(c.strength_mG, 0)} mG vs ` +
      `${fmt(c.wmm_strength_mG, 0)} mG, inclination ${fmt(c.inclination_error_deg, 1)}° off</td></tr>`);
    (c.cautions || []).forEach((t) => rows.push(`<tr><td colspan="3" class="warn">${escapeHtml(t)}</td></tr>`));
  }
  setHtml($("fy-table"), rows.join(""));
}

function render(s) {
  last = s;
  const w = s.wizard;
  setText($("status"), linkText(s) + (w.in_use ? " — calibration in use: " + inUseText(w) : ""));
  renderControl(w); renderSteps(w); renderCompasses(w); renderCoverage(w); renderOnboard(w);
  renderResult(w, s.source.autopilot); renderAfter(w); renderFixed(w);
  show("deviation-card", !!w.deviation);
  if (w.deviation) {
    setText($("deviation-text"), "max ±" + fmt(w.deviation.max_before_deg, 1) + "° before, ±" + fmt(w.deviation.max_after_deg, 1) + "° after" +
      (w.deviation.after_significant === false ? " (within the noise of the dance)" : ""));
    drawDeviation($("deviation"), w.deviation);
  }
}

// Whose calibration corrects the heading, and where it is applied.
function inUseText(w) {
  if (w.in_use === "station") return "this station's";
  if (w.onboard && w.onboard.state === "accepted") return "the vehicle's own calibrator's";
  if (w.mode === "fixed_yaw" && w.fixed_yaw) return "the vehicle's (calibrated at a known heading)";
  const pw = w.param_write;
  if ((pw && pw.state === "written") || (w.result && w.result.status === "ok" && w.state === "accepted"))
    return "this station's, in the vehicle";
  return "the vehicle's";
}

function guarded(fn) {
  return async () => { $("cal-error").textContent = ""; try { await fn(); } catch (e) { $("cal-error").textContent = e.message; } };
}
const mode = () => document.querySelector("#modes input:checked").value;
const num = (id) => { const v = parseFloat($(id).value); if (Number.isNaN(v)) throw new Error("enter a number of degrees"); return v; };
const ACTIONS = {
  start: () => api("POST", "/api/calibration/start", { mode: mode() }),
  reset: () => api("POST", "/api/calibration/reset"),
  redo: async () => { await api("POST", "/api/calibration/reset"); await api("POST", "/api/calibration/start", { mode: mode() }); },
};
// Start over, Reset and Redo ask first when they would throw a result or a written state away.
function asking(action) {
  return guarded(async () => {
    if (last && wouldLose(last.wizard)) { discardAsked = action; render(last); return; }
    await ACTIONS[action]();
  });
}
$("start").onclick = asking("start");
$("reset").onclick = asking("reset");
$("redo").onclick = asking("redo");
$("discard-yes").onclick = guarded(async () => { const a = discardAsked; discardAsked = null; if (a) await ACTIONS[a](); });
$("discard-no").onclick = () => { discardAsked = null; if (last) render(last); };
document.querySelectorAll("#modes input").forEach((r) => { r.onchange = () => { modeChosen = true; }; });
$("finish").onclick = guarded(() => api("POST", "/api/calibration/finish"));
$("accept").onclick = guarded(() => api("POST", "/api/calibration/accept", { which: "ours" }));
$("ob-accept").onclick = guarded(() => api("POST", "/api/calibration/accept", { which: "vehicle" }));
$("ob-cancel").onclick = guarded(() => api("POST", "/api/calibration/onboard/cancel"));
$("fitness").onchange = guarded(() => api("PUT", "/api/calibration/fitness", { level: $("fitness").value }));
$("compass-table").addEventListener("change", (e) => {
  const k = e.target.dataset.compass;
  if (k !== undefined) guarded(() => api("PUT", "/api/calibration/compasses/" + k, { included: e.target.checked }))();
});
$("reboot").onclick = () => { rebootAsked = true; if (last) render(last); };
$("reboot-no").onclick = () => { rebootAsked = false; if (last) render(last); };
$("reboot-yes").onclick = guarded(async () => { rebootAsked = false; await api("POST", "/api/calibration/reboot", { confirm: true }); });
$("hc-measure").onclick = guarded(() => api("POST", "/api/calibration/heading-check", { kind: "bearing", bearing_deg: num("hc-bearing") }));
$("hc-walk").onclick = guarded(() => api("POST", "/api/calibration/heading-check", { kind: "walk" }));
$("hc-walk-stop").onclick = guarded(() => api("POST", "/api/calibration/heading-check/stop"));
$("fy-send").onclick = guarded(() => api("POST", "/api/calibration/fixed-yaw", { yaw_deg: num("fy-yaw"), source: "entered" }));
$("fy-walk").onclick = guarded(() => api("POST", "/api/calibration/heading-check", { kind: "walk" }));
$("fy-walk-stop").onclick = guarded(() => api("POST", "/api/calibration/heading-check/stop"));
$("fy-gps").onclick = guarded(() => api("POST", "/api/calibration/fixed-yaw", { source: "gps" }));
$("export").onclick = () => {
  const ap = $("export-ap").value;
  location.href = "/api/calibration/params" + (ap ? "?autopilot=" + ap : "");
};

api("GET", "/api/calibration/sections").then((c) => { sectionCentres = c; }).catch((e) => console.error(e));
connectState(render, (up) => { if (!up) $("status").textContent = "station connection lost, retrying…"; });
setupViewer("viewer", "initialCameraPosition=-4.8,1.7,4.2&initialCameraLookAt=0,1.7,1.2");
