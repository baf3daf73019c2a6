// Calibration page drawings: the sphere of field directions covered, and the deviation card.
"use strict";

// The 100 equal-area cells of estimators.calibration.coverage_cells: 10 bands equal in z, 10 sectors
// equal in longitude (atan2(y, x) + pi); cell = band * 10 + sector.
const BANDS = 10, SECTORS = 10;

function cellOutline(cell) {
  const band = Math.floor(cell / SECTORS), sector = cell % SECTORS;
  const z0 = -1 + 2 * band / BANDS, z1 = z0 + 2 / BANDS;
  const l0 = 2 * Math.PI * sector / SECTORS - Math.PI, l1 = l0 + 2 * Math.PI / SECTORS;
  const pts = [], n = 6;
  const at = (z, l) => { const r = Math.sqrt(Math.max(0, 1 - z * z)); return [r * Math.cos(l), r * Math.sin(l), z]; };
  for (let i = 0; i <= n; i++) pts.push(at(z0, l0 + (l1 - l0) * i / n));
  for (let i = 0; i <= n; i++) pts.push(at(z0 + (z1 - z0) * i / n, l1));
  for (let i = 0; i <= n; i++) pts.push(at(z1, l1 - (l1 - l0) * i / n));
  for (let i = 0; i <= n; i++) pts.push(at(z1 - (z1 - z0) * i / n, l0));
  return { pts, upper: z1 <= 0 };
}
const CELL_OUTLINES = Array.from({ length: BANDS * SECTORS }, (_, i) => cellOutline(i));

// Two discs: directions toward the vehicle's top (body z <= 0) and bottom (z >= 0), seen from above,
// nose (+x) up the page, right (+y) to the right.
function drawSphere(canvas, cells, current, sections, sectionCentres) {
  const ctx = canvas.getContext("2d"), W = canvas.width, H = canvas.height;
  ctx.clearRect(0, 0, W, H);
  const R = Math.min(W / 4 - 8, H / 2 - 14), discs = [[W / 4, H / 2 + 6, "top half"], [3 * W / 4, H / 2 + 6, "bottom half"]];
  const proj = (p, d) => [discs[d][0] + R * p[1], discs[d][1] - R * p[0]];
  discs.forEach(([cx, cy, label]) => {
    ctx.fillStyle = "#eef1f4"; ctx.beginPath(); ctx.arc(cx, cy, R, 0, 2 * Math.PI); ctx.fill();
    ctx.fillStyle = "#68727d"; ctx.font = "11px system-ui"; ctx.textAlign = "center";
    ctx.fillText(label + " (nose ↑)", cx, cy - R - 3);
  });
  CELL_OUTLINES.forEach((c, i) => {
    const d = c.upper ? 0 : 1, covered = cells && cells[i] === "1";
    ctx.beginPath();
    c.pts.forEach((p, k) => { const [x, y] = proj(p, d); if (k) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
    ctx.closePath();
    ctx.fillStyle = covered ? "#43a047" : "#d5dbe1"; ctx.fill();
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 0.7; ctx.stroke();
  });
  if (sections && sectionCentres) {
    sectionCentres.forEach((c, i) => {
      const [x, y] = proj(c, c[2] <= 0 ? 0 : 1);
      ctx.beginPath(); ctx.arc(x, y, 3, 0, 2 * Math.PI);
      if (sections.includes(i)) { ctx.fillStyle = "#1565c0"; ctx.fill(); } else { ctx.strokeStyle = "#1565c0"; ctx.lineWidth = 1; ctx.stroke(); }
    });
  }
  if (current) {
    const [x, y] = proj(current, current[2] <= 0 ? 0 : 1);
    ctx.beginPath(); ctx.arc(x, y, 5, 0, 2 * Math.PI); ctx.fillStyle = "#c62828"; ctx.fill();
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 1.5; ctx.stroke();
  }
}

// Heading error (deg) against heading: before (orange) and after (green).
function drawDeviation(canvas, card) {
  const ctx = canvas.getContext("2d"), W = canvas.width, H = canvas.height;
  ctx.clearRect(0, 0, W, H);
  if (!card || !card.heading_deg.length) return;
  const left = 34, right = W - 8, top = 8, bottom = H - 20;
  const m = Math.max(2, ...card.before_deg.map(Math.abs), ...card.after_deg.map(Math.abs));
  const span = Math.ceil(m / 5) * 5;
  const X = (h) => left + (right - left) * h / 360, Y = (e) => top + (bottom - top) * (span - e) / (2 * span);
  ctx.strokeStyle = "#c3ccd6"; ctx.lineWidth = 1; ctx.fillStyle = "#68727d"; ctx.font = "10px system-ui";
  ctx.textAlign = "center";
  for (let h = 0; h <= 360; h += 90) { ctx.beginPath(); ctx.moveTo(X(h), top); ctx.lineTo(X(h), bottom); ctx.stroke(); ctx.fillText(h + "°", X(h), H - 6); }
  ctx.textAlign = "right";
  [-span, 0, span].forEach((e) => { ctx.beginPath(); ctx.moveTo(left, Y(e)); ctx.lineTo(right, Y(e)); ctx.stroke(); ctx.fillText((e > 0 ? "+" : "") + e + "°", left - 3, Y(e) + 3); });
  [[card.before_deg, "#ef6c00"], [card.after_deg, "#2e7d32"]].forEach(([v, colour]) => {
    ctx.strokeStyle = colour; ctx.fillStyle = colour; ctx.lineWidth = 2; ctx.beginPath();
    card.heading_deg.forEach((h, i) => { if (i) ctx.lineTo(X(h), Y(v[i])); else ctx.moveTo(X(h), Y(v[i])); });
    ctx.stroke();
    card.heading_deg.forEach((h, i) => { ctx.beginPath(); ctx.arc(X(h), Y(v[i]), 2.5, 0, 2 * Math.PI); ctx.fill(); });
  });
}
