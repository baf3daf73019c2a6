// Shared by the pages: REST helper and the state WebSocket (reconnects by itself).
"use strict";

// Writes carry the station's page token (X-MagStation-Token): the station refuses state changes
// from other origins and from pages that cannot read /api/page-token (see README, API and security).
let pageToken = null;
function writeToken(refresh) {
  if (refresh || !pageToken) {
    pageToken = fetch("/api/page-token", { credentials: "same-origin" })
      .then((r) => (r.ok ? r.json() : Promise.reject(new Error("page token: " + r.status))))
      .then((d) => d.token)
      .catch((e) => { pageToken = null; throw e; });
  }
  return pageToken;
}
writeToken(false).catch(() => {});   // fetched ahead, so a click goes out at once

// A page's state changes reach the station in the order the user made them (a pause then a seek
// must not arrive as a seek then a pause on a busy machine): each write waits for the one before.
let writesDone = Promise.resolve();
function api(method, path, body) {
  if (method === "GET" || method === "HEAD") return request(method, path, body);
  const sent = writesDone.then(() => request(method, path, body));
  writesDone = sent.catch(() => {});
  return sent;
}

async function request(method, path, body) {
  const opts = { method, headers: {}, credentials: "same-origin" };
  if (body !== undefined) { opts.headers["Content-Type"] = "application/json"; opts.body = JSON.stringify(body); }
  const writes = method !== "GET" && method !== "HEAD";
  if (writes) opts.headers["X-MagStation-Token"] = await writeToken(false);
  let res = await fetch(path, opts);
  if (writes && res.status === 403) {   // the station restarted: a new page token
    opts.headers["X-MagStation-Token"] = await writeToken(true);
    res = await fetch(path, opts);
  }
  const text = await res.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch (e) { data = text; }
  if (!res.ok) throw new Error((data && data.detail) ? (typeof data.detail === "string" ? data.detail : JSON.stringify(data.detail)) : res.statusText);
  return data;
}

// Write only what changed.  A state arrives up to 50 times a second and every render sets the
// whole page; writing the same text or markup again still makes the browser rebuild, lay out and
// paint it (a page with a replay running took half a core for that), and replacing a table under
// the pointer would swallow clicks on it.
const lastHtml = new WeakMap();
function setText(el, value) {
  const text = value === null || value === undefined ? "" : String(value);
  if (el.textContent !== text) el.textContent = text;
}
function setHtml(el, html) { if (lastHtml.get(el) !== html) { lastHtml.set(el, html); el.innerHTML = html; } }
// A property (hidden, disabled, className, a dataset or style entry...) set only when it differs:
// writing the same value writes the attribute again (a DOM mutation for nothing).
function setProp(el, name, value) {
  if (typeof el[name] === "boolean") value = !!value;
  if (el[name] !== value) el[name] = value;
}

// The pages draw a state at most this often. The station pushes up to 50 states a second (the
// live latency is measured at the push); text and tables drawn 20 times a second read the same to
// an operator and cost the browser half as much (benchmarks/page_cpu.py).
const DRAW_INTERVAL_MS = 50;

function connectState(onState, onLink) {
  // Renders only the newest state: if the page falls behind (slow machine, hidden tab), queued
  // pushes are skipped instead of being drawn one by one, so the view never lags the station.
  let ws = null, retry = 500, latest = null, scheduled = false, drawnAt = -Infinity;
  function draw() {
    scheduled = false;
    drawnAt = performance.now();
    try { onState(JSON.parse(latest)); } catch (e) { console.error(e); }
  }
  function open() {
    ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
    ws.onopen = () => { retry = 500; onLink(true); };
    ws.onmessage = (ev) => {
      latest = ev.data;
      ws.send("ack");   // flow control: the station sends the next state once we have this one
      if (!scheduled) {
        scheduled = true;
        setTimeout(draw, Math.max(0, drawnAt + DRAW_INTERVAL_MS - performance.now()));
      }
    };
    ws.onclose = () => { onLink(false); setTimeout(open, retry); retry = Math.min(retry * 2, 5000); };
  }
  open();
}

// camera: "initialCameraPosition=x,y,z&initialCameraLookAt=x,y,z" (viser world, see scene.py)
async function setupViewer(frameId, camera) {
  try {
    const h = await api("GET", "/api/health");
    if (h.viser_port) document.getElementById(frameId).src = location.protocol + "//" + location.hostname + ":" +
      h.viser_port + "/" + (camera ? "?" + camera : "");
  } catch (e) { console.error(e); }
}

function fmt(v, digits = 1, unit = "") {
  return (v === null || v === undefined || Number.isNaN(v)) ? "—" : Number(v).toFixed(digits) + unit;
}

function escapeHtml(s) {
  return String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
}

function linkText(s) {
  const src = s.source;
  if (src.kind === "none") return "no source";
  let t = src.kind + ": " + src.name;
  if (src.kind === "live") t += " — link " + src.link + (s.rx_age_s !== null ? " (last packet " + fmt(s.rx_age_s, 1) + " s ago)" : "");
  if (src.autopilot) t += " — " + src.autopilot;
  return t;
}
