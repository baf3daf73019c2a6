// Small canvas plots for the station page: time on x, nice ticks, gaps where data is missing,
// headings broken at the 0/360 wrap (no false jump), alarm intervals shaded.
"use strict";

// Tick values covering [lo, hi] with a 1/2/5 x 10^k step; labels keep their sign.
function niceTicks(lo, hi, count = 4) {
  if (!(hi > lo)) { hi = lo + 1; lo = lo - 1; }
  const raw = (hi - lo) / count, mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= raw) || 10 * mag;
  const digits = Math.max(0, -Math.floor(Math.log10(step) + 1e-9));
  const ticks = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) {
    const r = Math.abs(v) < step * 1e-6 ? 0 : v;      // no "-0"
    ticks.push({ value: r, label: r.toFixed(digits) });
  }
  return ticks;
}

// Split a series into drawable runs: a gap where a value is null, and (wrap=true) where a
// heading crosses 0/360 (the step between neighbours is more than 180 deg).
function runs(t, y, wrap) {
  const out = [];
  let cur = [];
  for (let i = 0; i < t.length; i++) {
    const v = y[i];
    if (v === null || v === undefined || t[i] === null) { if (cur.length) out.push(cur); cur = []; continue; }
    if (wrap && cur.length && Math.abs(v - cur[cur.length - 1][1]) > 180) { out.push(cur); cur = []; }
    cur.push([t[i], v]);
  }
  if (cur.length) out.push(cur);
  return out;
}

// series: [{label, color, y: [...], wrap, dots, dash}]; opts: {t, t0, t1, ymin, ymax, alarms, refs, yTicks}
function drawPlot(canvas, series, opts) {
  const dpr = window.devicePixelRatio || 1, w = canvas.clientWidth, h = canvas.clientHeight;
  if (!w || !h) return;
  if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
    canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
  }
  const g = canvas.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  g.font = "11px system-ui, sans-serif";
  const L = 46, R = 8, T = 18, B = 18, pw = w - L - R, ph = h - T - B;
  let lo = opts.ymin, hi = opts.ymax;
  if (lo === undefined || hi === undefined) {
    const vals = series.flatMap((s) => s.y).concat((opts.refs || []).map((r) => r.value)).filter((v) => v !== null && v !== undefined);
    lo = vals.length ? Math.min(...vals) : -1; hi = vals.length ? Math.max(...vals) : 1;
    const pad = (hi - lo) * 0.08 || Math.max(Math.abs(hi) * 0.1, 0.5);
    lo -= pad; hi += pad;
  }
  const t0 = opts.t0, t1 = opts.t1 > opts.t0 ? opts.t1 : opts.t0 + 1;
  const X = (t) => L + (t - t0) / (t1 - t0) * pw, Y = (v) => T + (hi - v) / (hi - lo) * ph;
  g.fillStyle = "rgba(220,0,0,0.12)";
  for (const a of opts.alarms || []) {
    const x0 = Math.max(L, X(a.start_s)), x1 = Math.min(L + pw, X(a.end_s === null ? t1 : a.end_s));
    if (x1 > x0) g.fillRect(x0, T, x1 - x0, ph);
  }
  g.strokeStyle = "#d6dbe1"; g.fillStyle = "#4b5561"; g.lineWidth = 1;
  const yt = (opts.yTicks || niceTicks)(lo, hi, ph > 90 ? 4 : 3);
  canvas.dataset.yticks = yt.map((k) => k.label).join(" ");
  canvas.dataset.yrange = lo.toFixed(1) + " " + hi.toFixed(1);
  g.textAlign = "right"; g.textBaseline = "middle";
  for (const k of yt) { const y = Y(k.value); g.beginPath(); g.moveTo(L, y); g.lineTo(L + pw, y); g.stroke(); g.fillText(k.label, L - 4, y); }
  g.textAlign = "center"; g.textBaseline = "top";
  // time ticks; the last one carries the unit ("170 s")
  const tt = niceTicks(t0, t1, Math.max(2, Math.floor(pw / 90))).filter((k) => X(k.value) >= L && X(k.value) <= L + pw);
  tt.forEach((k, i) => {
    const text = i === tt.length - 1 ? k.label + " s" : k.label;
    g.fillText(text, Math.min(X(k.value), w - 1 - g.measureText(text).width / 2), T + ph + 3);   // kept on the canvas
  });
  g.save(); g.beginPath(); g.rect(L, T, pw, ph); g.clip();
  for (const r of opts.refs || []) {
    if (r.value === null) continue;
    g.strokeStyle = r.color; g.lineWidth = 2; g.setLineDash([6, 4]); g.beginPath(); g.moveTo(L, Y(r.value)); g.lineTo(L + pw, Y(r.value)); g.stroke();
  }
  g.setLineDash([]);
  for (const s of series) {
    g.strokeStyle = g.fillStyle = s.color; g.lineWidth = s.width || 1.5;
    for (const run of runs(opts.t, s.y, s.wrap)) {
      if (s.dots) { for (const [t, v] of run) g.fillRect(X(t) - 1.5, Y(v) - 1.5, 3, 3); continue; }
      g.beginPath();
      run.forEach(([t, v], i) => (i ? g.lineTo(X(t), Y(v)) : g.moveTo(X(t), Y(v))));
      g.stroke();
    }
  }
  g.restore();
  g.textAlign = "left"; g.textBaseline = "top"; g.fillStyle = "#1d232b";
  g.fillText(canvas.dataset.title || "", L, 3);
  let x = L + g.measureText(canvas.dataset.title || "").width + 12;
  for (const s of series.concat((opts.refs || []).filter((r) => r.value !== null))) {
    g.fillStyle = s.color; g.fillRect(x, 7, 10, 3); x += 13;
    g.fillStyle = "#4b5561"; g.fillText(s.label, x, 3); x += g.measureText(s.label).width + 10;
  }
}
