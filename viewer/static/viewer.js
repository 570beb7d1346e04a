// arena view: draws the snapshots the server streams by Server-Sent Events (/events); each one
// carries the accumulated event image rendered at the same moment (data URL in `frame`) when it
// changed. No build step, no dependencies.
"use strict";

const $ = (id) => document.getElementById(id);
window.arenaState = null;      // last snapshot, also read by the tests
window.arenaFrames = 0;        // event images loaded so far

function colour(label) {       // a stable colour per track label; labels differing by one
  let h = 0;                   // character get hues 137.5 degrees apart (golden angle)
  for (const c of String(label)) h = (h * 31 + c.charCodeAt(0)) % 1000003;
  return `hsl(${(h * 137.508) % 360}, 85%, 40%)`;
}

function fmt(v, nd = 2) { return v === null || v === undefined ? "–" : Number(v).toFixed(nd); }

function esc(s) {
  return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));
}

// ---- overlay on the event image (sensor px) --------------------------------------------------
function arrow(ctx, x0, y0, x1, y1, head) {
  const a = Math.atan2(y1 - y0, x1 - x0);
  ctx.beginPath();
  ctx.moveTo(x0, y0); ctx.lineTo(x1, y1);
  ctx.lineTo(x1 - head * Math.cos(a - 0.5), y1 - head * Math.sin(a - 0.5));
  ctx.moveTo(x1, y1);
  ctx.lineTo(x1 - head * Math.cos(a + 0.5), y1 - head * Math.sin(a + 0.5));
  ctx.stroke();
}

function drawOverlay(s) {
  const cv = $("overlay"), im = s.image;
  if (!im.width) return;
  // a sensor larger than the viewer's largest image comes downsampled by im.scale: the canvas has
  // the image's size, the drawing stays in sensor px
  const k = im.scale || 1, cw = Math.ceil(im.width / k), ch = Math.ceil(im.height / k);
  if (cv.width !== cw || cv.height !== ch) { cv.width = cw; cv.height = ch; }
  const ctx = cv.getContext("2d");
  const lw = Math.max(1, im.width / 400);
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.clearRect(0, 0, cv.width, cv.height);
  ctx.setTransform(1 / k, 0, 0, 1 / k, 0, 0);
  ctx.lineWidth = lw;
  ctx.font = `${Math.round(12 * lw)}px system-ui, sans-serif`;
  for (const t of s.tracks) {
    if (!t.uv) continue;
    const c = colour(t.label);
    ctx.strokeStyle = c; ctx.fillStyle = c;
    ctx.globalAlpha = 0.6;
    ctx.beginPath();
    t.trail_px.forEach(([u, v], i) => (i ? ctx.lineTo(u, v) : ctx.moveTo(u, v)));
    ctx.stroke();
    ctx.globalAlpha = t.state === "confirmed" ? 1 : 0.5;
    ctx.beginPath();
    if (t.box_px) {
      t.box_px.forEach(([u, v], i) => (i ? ctx.lineTo(u, v) : ctx.moveTo(u, v)));
      ctx.closePath();
    } else {
      ctx.rect(t.uv[0] - 10 * lw, t.uv[1] - 10 * lw, 20 * lw, 20 * lw);
    }
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 4 * lw; ctx.stroke();   // halo: visible on events too
    ctx.strokeStyle = c; ctx.lineWidth = 2 * lw; ctx.stroke(); ctx.lineWidth = lw;
    if (t.heading_px) { ctx.lineWidth = 2 * lw; arrow(ctx, t.uv[0], t.uv[1], t.heading_px[0], t.heading_px[1], 6 * lw); ctx.lineWidth = lw; }
    ctx.fillText(t.label, t.uv[0] + 12 * lw, t.uv[1] - 12 * lw);
    ctx.globalAlpha = 1;
  }
  ctx.strokeStyle = "#0a0";
  for (const g of s.groundtruth) {
    if (!g.uv) continue;
    ctx.beginPath(); ctx.arc(g.uv[0], g.uv[1], 4 * lw, 0, 2 * Math.PI); ctx.stroke();
  }
}

// ---- arena plot (metres, y up) ---------------------------------------------------------------
function drawArena(s) {
  const cv = $("arena"), ctx = cv.getContext("2d");
  const [W, H] = s.arena_size_m, pad = 24;
  const k = Math.min((cv.width - 2 * pad) / W, (cv.height - 2 * pad) / H);
  const X = (x) => pad + x * k, Y = (y) => cv.height - pad - y * k;
  ctx.clearRect(0, 0, cv.width, cv.height);
  ctx.strokeStyle = "#ddd"; ctx.fillStyle = "#888"; ctx.lineWidth = 1; ctx.font = "10px system-ui";
  for (let g = 0; g <= Math.max(W, H) + 1e-9; g += 0.5) {
    if (g <= W) { ctx.beginPath(); ctx.moveTo(X(g), Y(0)); ctx.lineTo(X(g), Y(H)); ctx.stroke(); ctx.fillText(g.toFixed(1), X(g) - 6, Y(0) + 12); }
    if (g <= H) { ctx.beginPath(); ctx.moveTo(X(0), Y(g)); ctx.lineTo(X(W), Y(g)); ctx.stroke(); ctx.fillText(g.toFixed(1), 2, Y(g) + 3); }
  }
  ctx.strokeStyle = "#444"; ctx.strokeRect(X(0), Y(H), W * k, H * k);
  for (const g of s.groundtruth) {
    ctx.strokeStyle = "#0a0"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(X(g.x), Y(g.y), 7, 0, 2 * Math.PI); ctx.stroke();
  }
  for (const t of s.tracks) {
    const c = colour(t.label);
    ctx.strokeStyle = c; ctx.fillStyle = c; ctx.lineWidth = 1.5;
    ctx.globalAlpha = 0.5;
    ctx.beginPath();
    t.trail_m.forEach(([x, y], i) => (i ? ctx.lineTo(X(x), Y(y)) : ctx.moveTo(X(x), Y(y))));
    ctx.stroke();
    ctx.globalAlpha = 1;
    ctx.beginPath(); ctx.arc(X(t.x), Y(t.y), 4, 0, 2 * Math.PI); ctx.fill();
    if (t.yaw !== null) arrow(ctx, X(t.x), Y(t.y), X(t.x + 0.12 * Math.cos(t.yaw)), Y(t.y + 0.12 * Math.sin(t.yaw)), 5);
    ctx.font = "11px system-ui"; ctx.fillText(t.label, X(t.x) + 7, Y(t.y) - 7);
  }
}

// ---- tables and sparklines -------------------------------------------------------------------
function drawTracks(s) {
  $("tracks").tBodies[0].innerHTML = s.tracks.map((t) => {
    // computed by the server: the robot's ground truth vs the track at that pose's stamp
    const err = t.error_m !== null && t.error_m !== undefined ? fmt(t.error_m, 3) : esc(t.error_note || "–");
    const hd = t.yaw === null ? null : ((((t.yaw * 180) / Math.PI + 180) % 360) + 360) % 360 - 180;
    return `<tr data-track="${esc(t.key)}"><td style="color:${colour(t.label)}">${esc(t.label)}</td><td>${fmt(t.x, 3)}</td>` +
      `<td>${fmt(t.y, 3)}</td><td>${fmt(hd, 0)}</td><td>${fmt(t.speed, 2)}</td><td>${esc(t.state)}</td>` +
      `<td>${t.n_events}</td><td>${err}</td><td>${fmt(t.latency_ms, 0)}</td></tr>`;
  }).join("");
}

function spark(values, w = 150, h = 30) {
  const cv = document.createElement("canvas");
  cv.width = w; cv.height = h;
  const ctx = cv.getContext("2d");
  if (values.length > 1) {
    let lo = Math.min(...values), hi = Math.max(...values);
    if (hi - lo < 1e-9) { lo -= 1; hi += 1; }
    ctx.strokeStyle = "#1f6feb"; ctx.lineWidth = 1.2; ctx.beginPath();
    values.forEach((v, i) => {
      const x = (i / (values.length - 1)) * (w - 2) + 1, y = h - 2 - ((v - lo) / (hi - lo)) * (h - 4);
      i ? ctx.lineTo(x, y) : ctx.moveTo(x, y);
    });
    ctx.stroke();
  }
  return cv;
}

function drawTelemetry(s) {
  const box = $("telemetry"), robots = Object.keys(s.telemetry);
  if (!robots.length) return;
  box.innerHTML = "";
  for (const r of robots) {
    const h = s.telemetry[r], div = document.createElement("div");
    div.className = "robot";
    div.innerHTML = `<b>${esc(r)}</b>`;
    for (const [name, vals, nd] of [["left wheel", h.speed_left, 2], ["right wheel", h.speed_right, 2],
                                    ["gyro z", h.gyro_z, 2], ["battery mV", h.battery_mv, 0]]) {
      const row = document.createElement("div");
      row.className = "spark";
      row.innerHTML = `<span>${name} ${fmt(vals[vals.length - 1], nd)}</span>`;
      row.appendChild(spark(vals));
      div.appendChild(row);
    }
    box.appendChild(div);
  }
}

function drawServices(s) {
  const kv = (o) => Object.entries(o || {}).map(([k, v]) => `${esc(k)}=${esc(typeof v === "number" ? +v.toPrecision(4) : v)}`).join(" ");
  $("services").tBodies[0].innerHTML = s.services.map((v) =>
    `<tr class="${v.stale ? "stale" : ""}"><td><span class="dot ${v.alive ? "alive" : ""}" title="${v.alive ? "alive" : "gone"}"></span></td>` +
    `<td>${esc(v.role)}</td><td>${esc(v.name)}</td><td>${esc(v.state || "–")}</td><td>${kv(v.rates)}</td>` +
    `<td>${kv(v.gauges)}</td><td title="${esc(v.last_error || "")}">${v.errors ?? "–"}${v.last_error ? " · " + esc(v.last_error.slice(0, 60)) : ""}</td></tr>`
  ).join("");
}

function render(s) {
  if (s.frame) {
    $("frame").src = s.frame;
    $("noevents").style.display = "none";
    window.arenaFrames += 1;
    delete s.frame;
  }
  window.arenaState = s;
  const im = s.image;
  $("caminfo").textContent = im.width ? `${im.camera || ""} ${im.width}×${im.height} px · last ${im.accumulate_ms} ms · ` +
    `${im.events} events · window ${im.seq ?? "–"} · dropped ${im.dropped ?? 0}` : "";
  $("summary").textContent = `${s.tracks.length} tracks · ${s.services.filter((v) => v.alive).length} services alive` +
    (s.calibrated ? "" : " · no calibration: tracks drawn where they carry pixel positions");
  drawOverlay(s); drawArena(s); drawTracks(s); drawTelemetry(s); drawServices(s);
}

const es = new EventSource("/events");
es.onopen = () => { $("conn").textContent = "live"; $("conn").className = "ok"; };
es.onerror = () => { $("conn").textContent = "disconnected, retrying…"; $("conn").className = "bad"; };
es.onmessage = (e) => render(JSON.parse(e.data));
