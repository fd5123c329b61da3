// clothd dashboard: live status over the WebSocket, the annotated MJPEG view, plots, and controls.
"use strict";

const $ = (id) => document.getElementById(id);
const HISTORY = 300;
const samples = { mean: [], worst: [], p50: [], p99: [], features: [] };
let token = localStorage.getItem("clothd-token") || "";
let tableToPixel = null; // 3x3 homography, table plane (m) -> image (px)
let imageSize = [640, 480];

// -- the API ---------------------------------------------------------------------------------------

async function call(method, path, body) {
  const headers = { "Content-Type": "application/json" };
  if (token) headers.Authorization = `Bearer ${token}`;
  const r = await fetch(path, { method, headers, body: body ? JSON.stringify(body) : undefined });
  if (r.status === 401) {
    $("token-box").hidden = false;
    throw new Error("this daemon needs a token");
  }
  if (!r.ok) {
    const detail = await r.json().catch(() => ({}));
    const text = Array.isArray(detail.detail) ? detail.detail.map((d) => d.msg).join("; ") : detail.detail;
    throw new Error(text || `${r.status}`);
  }
  return r.json();
}

function say(text, refused = false) { $("message").textContent = text; $("message").classList.toggle("refused", refused); }

async function act(method, path, body) {
  try { const r = await call(method, path, body); say(r.detail || ""); } catch (e) { say(e.message, true); }
}

// -- live status -----------------------------------------------------------------------------------

const LINK_CLASS = { connected: "ok", starting: "warn" }; // connecting, disconnected: it was up, and is down
const FAULT_CODES = { 1: "WATCHDOG", 2: "STALL", 3: "OVERTEMP", 4: "ESTOP_INPUT" }; // docs/serial-protocol.md
const FAULTS_SHOWN = 5;
const WHOLE_BOARD = 0xffff;

function pill(el, text, cls) { el.textContent = text; el.className = `pill ${cls}`; }
function fmt(v, digits = 4) { return v === null || v === undefined ? "–" : Number(v).toFixed(digits); }
function push(key, v) { const a = samples[key]; a.push(v); if (a.length > HISTORY) a.shift(); }
function degToRad(deg) { return deg * Math.PI / 180; }
function angle(rad) { return rad === null || rad === undefined ? "–" : `${fmt(rad * 180 / Math.PI, 2)}° (${fmt(rad)} rad)`; }

function clock(tUnixS) { // the cell PC's local time of day, HH:MM:SS
  const d = new Date(tUnixS * 1000);
  return [d.getHours(), d.getMinutes(), d.getSeconds()].map((v) => String(v).padStart(2, "0")).join(":");
}

function banner(el, text) { el.hidden = !text; if (text) el.textContent = text; }

// Why nothing moves, at the top of the page: the e-stop, a halted move, or a start not finished.
function showBanners(s) {
  $("banner-estop").hidden = !s.estop;
  banner($("banner-halt"), s.halt_reason &&
    `Stopped by itself at ${clock(s.halt_t_unix_s)}: ${s.halt_reason}. The modules are idle until a new setpoint.`);
  banner($("banner-starting"), s.link.state === "starting" &&
    `Starting: waiting for the stepper controller${s.link.last_error ? ` (${s.link.last_error})` : ""}.`);
}

function showFaults(faults) {
  const items = faults.slice(-FAULTS_SHOWN).reverse().map((f) => {
    const where = f.module === WHOLE_BOARD ? "whole board" : `module ${f.module}`;
    const name = FAULT_CODES[f.code] || `code ${f.code}`;
    return `${clock(f.t_unix_s)} · ${where} · ${name}${f.text ? `: ${f.text}` : ""}`;
  });
  $("faults").replaceChildren(...(items.length ? items : ["none"]).map((text) => {
    const li = document.createElement("li"); li.textContent = text; return li;
  }));
}

const BASIS_WORDS = { measured: "measured", since_start: "since start" }; // status flatness.basis

// Every camera's state; a further one's skew to the first (median, ms) and the share of frames paired.
function showCameras(cameras) {
  $("cameras").textContent = cameras.map((c, i) => `${c.name} ${c.state} ${fmt(c.fps, 1)} fps` + (i === 0 ? "" :
    ` · skew ${c.skew_ms === null ? "–" : `${c.skew_ms >= 0 ? "+" : ""}${fmt(c.skew_ms, 1)}`} ms, ` +
    `${fmt(c.paired_pct, 0)} % paired`)).join(" | ") || "–";
  $("cameras").className = `small${cameras.some((c) => !c.healthy) ? " warn" : ""}`;
}

function show(s) {
  const stateCls = s.state === "tracking" ? "ok" : s.state === "starting" ? "warn" : "bad";
  pill($("state"), s.state, stateCls);
  pill($("mode"), `mode ${s.mode}`, s.mode === "idle" ? "" : "ok");
  pill($("camera"), `camera ${s.camera.state}`, s.camera.healthy ? "ok" : "bad");
  // A latched e-stop holds every command back at the link: its pill says so, never green.
  pill($("link"), `link ${s.link.state}${s.estop ? " · e-stop" : ""}`, s.estop ? "bad" : LINK_CLASS[s.link.state] || "bad");
  $("estop").classList.toggle("latched", s.estop);
  showBanners(s);
  showFaults(s.faults);
  const p = s.pose || {};
  $("pose-x").textContent = fmt(p.x_m); $("pose-y").textContent = fmt(p.y_m);
  $("pose-t").textContent = angle(p.theta_rad);
  const sp = s.setpoint || {};
  $("sp-x").textContent = fmt(sp.x_m); $("sp-y").textContent = fmt(sp.y_m);
  $("sp-t").textContent = angle(sp.theta_rad);
  $("features").textContent = s.features;
  const f = s.flatness;
  $("flatness").textContent = !f ? "–" : `${f.flat ? "flat" : "wrinkled"} · highest ${fmt(f.max_height_mm, 1)} mm · ` +
    `${fmt(f.compressed_area_pct, 1)} % holds slack · ${f.ridges.length} ridge${f.ridges.length === 1 ? "" : "s"}` +
    (f.flaps.length ? ` · ${f.flaps.length} flap${f.flaps.length === 1 ? "" : "s"} (fold back by hand)` : "");
  $("flatness").className = f && !f.flat ? "warn" : "";
  $("basis").textContent = !f ? "" : `· basis: ${BASIS_WORDS[f.basis] || f.basis}`;
  showCameras(s.cameras || []);
  showPieces(s.pieces);
  $("residual").textContent = `${fmt(s.residual.mean_px, 2)} / ${fmt(s.residual.worst_px, 2)} px`;
  const tick = s.timing.stages.compute || {};
  $("missed").textContent = s.timing.missed_ticks;
  $("late").textContent = s.timing.compute_overruns;  // ticks that went out with the previous commands
  const c = s.link.counters;
  $("counters").textContent = `sent ${c.sent} · acked ${c.acked} · retransmitted ${c.retransmitted} · ` +
    `invalid ${c.invalid} · faults ${c.faults} · reconnects ${c.reconnects} · RTT p50 ${fmt(c.rtt_p50_ms, 1)} ms`;
  push("mean", s.residual.mean_px); push("worst", s.residual.worst_px);
  push("p50", tick.p50_ms); push("p99", tick.p99_ms); push("features", s.features);
  plot($("plot-residual"), [[samples.mean, "#4fc3f7"], [samples.worst, "#ffb74d"]]);
  plot($("plot-tick"), [[samples.p50, "#4fc3f7"], [samples.p99, "#ffb74d"]]);
  plot($("plot-features"), [[samples.features, "#9ccc65"]]);
}

// -- mode flow's pieces (status pieces: those on the table, then the last gone) ---------------------

const PIECES_GONE_SHOWN = 10; // of the last 50 gone the status keeps, the newest
const PIECE_COLOURS = { entering: "#90a4ae", tracked: "#4fc3f7", flattening: "#ffb74d", placing: "#ba68c8",
  leaving: "#9ccc65", rejected: "#ef5350" };
const PIECE_ARROW_M = 0.05;

function onTable(p) { return p.left_t_mono_s === null && p.state !== "left"; }

function pieceRow(p) {
  const tr = document.createElement("tr");
  tr.className = p.state; tr.dataset.id = p.id;
  const pose = p.pose || {};
  const shape = p.flat === null ? "–" : `${p.flat ? "flat" : "wrinkled"} · ${fmt(p.max_height_mm, 1)} mm`;
  const cells = [`#${p.id}`, onTable(p) ? p.state : `${p.state} (gone)`, `${fmt(pose.x_m, 3)}, ${fmt(pose.y_m, 3)}`,
    pose.theta_rad === null || pose.theta_rad === undefined ? "–" : `${fmt(pose.theta_rad * 180 / Math.PI, 1)}°`, shape];
  tr.replaceChildren(...cells.map((text) => { const td = document.createElement("td"); td.textContent = text; return td; }));
  if (!p.reason) return [tr];
  const why = document.createElement("tr"); why.className = p.state;
  const td = document.createElement("td"); td.colSpan = 5; td.className = "reason"; td.textContent = `#${p.id}: ${p.reason}`;
  why.append(td);
  return [tr, why];
}

// Every piece on the table, then the newest gone; each posed piece drawn over the video (an arrow along its heading).
function showPieces(pieces) {
  $("pieces-panel").hidden = !pieces;
  drawPieces(pieces || []);
  if (!pieces) return;
  const table = pieces.filter(onTable), gone = pieces.filter((p) => !onTable(p));
  const shown = [...table, ...gone.slice(-PIECES_GONE_SHOWN).reverse()];
  $("pieces-rows").replaceChildren(...shown.flatMap(pieceRow));
  const rejects = gone.filter((p) => p.state === "rejected").length;
  $("pieces-summary").textContent = `${table.length} on the table · last ${gone.length} gone, ${rejects} rejected` +
    (gone.length > PIECES_GONE_SHOWN ? ` (newest ${PIECES_GONE_SHOWN} shown)` : "");
}

function drawPieces(pieces) {
  const canvas = $("pieces-view");
  canvas.width = imageSize[0]; canvas.height = imageSize[1];
  if (!tableToPixel) return;
  const g = canvas.getContext("2d");
  g.lineWidth = 3; g.font = "bold 16px sans-serif";
  for (const p of pieces.filter((q) => onTable(q) && q.pose && q.pose.x_m !== null)) {
    const { x_m: x, y_m: y, theta_rad: t } = p.pose;
    const [u, v] = toPixel(x, y);
    const [a, b] = toPixel(x + PIECE_ARROW_M * Math.cos(t), y + PIECE_ARROW_M * Math.sin(t));
    g.strokeStyle = g.fillStyle = PIECE_COLOURS[p.state] || "#fff";
    g.beginPath(); g.arc(u, v, 6, 0, 2 * Math.PI); g.moveTo(u, v); g.lineTo(a, b); g.stroke();
    g.fillText(`#${p.id}`, u + 8, v - 8);
  }
}

function plot(canvas, series) {
  const g = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height;
  g.clearRect(0, 0, w, h);
  const values = series.flatMap(([a]) => a.filter((v) => v !== null && v !== undefined));
  const top = Math.max(1e-9, ...values) * 1.1;
  g.fillStyle = "#778"; g.font = "10px sans-serif"; g.fillText(top.toPrecision(3), 2, 10);
  for (const [a, colour] of series) {
    g.strokeStyle = colour; g.beginPath();
    a.forEach((v, i) => {
      if (v === null || v === undefined) return;
      const x = (i / (HISTORY - 1)) * w, y = h - (v / top) * h;
      i === 0 ? g.moveTo(x, y) : g.lineTo(x, y);
    });
    g.stroke();
  }
}

let backoff = 1000;
function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/v1/stream?hz=10`);
  ws.onopen = () => { backoff = 1000; pill($("stream"), "stream live", "ok"); };
  ws.onmessage = (ev) => show(JSON.parse(ev.data));
  ws.onclose = () => {
    pill($("stream"), "stream reconnecting", "bad");
    setTimeout(connect, backoff);
    backoff = Math.min(backoff * 2, 5000);
  };
}

// The MJPEG view reconnects by itself when its stream drops.
$("video").onerror = () => setTimeout(() => { $("video").src = `/api/v1/view.mjpg?t=${Date.now()}`; }, 1000);

// -- controls --------------------------------------------------------------------------------------

function estop() { act("POST", "/api/v1/estop"); }
$("estop").onclick = estop;
document.addEventListener("keydown", (ev) => { if (ev.key === "Escape") { ev.preventDefault(); estop(); } });
$("estop-clear").onclick = () => act("POST", "/api/v1/estop/clear");
$("reset").onclick = () => act("POST", "/api/v1/reset");
$("token-save").onclick = () => {
  token = $("token").value; localStorage.setItem("clothd-token", token); $("token-box").hidden = true; say("");
};
// θ is entered in degrees; the API takes radians, shown under the form as they will be sent.
function enteredThetaRad() { return degToRad(Number($("in-t").value)); }
function showEnteredThetaRad() { $("in-t-rad").textContent = `θ = ${fmt(enteredThetaRad())} rad`; }
$("in-t").oninput = showEnteredThetaRad;
$("setpoint-form").onsubmit = (ev) => {
  ev.preventDefault();
  const mode = $("mode-select").value;
  const body = mode === "move"
    ? { mode, x_m: Number($("in-x").value), y_m: Number($("in-y").value), theta_rad: enteredThetaRad() }
    : { mode };
  act("PUT", "/api/v1/setpoint", body);
};

// -- dragging a target pose on the video -----------------------------------------------------------

function invert3(m) {
  const [a, b, c] = m[0], [d, e, f] = m[1], [g, h, i] = m[2];
  const A = e * i - f * h, B = -(d * i - f * g), C = d * h - e * g;
  const det = a * A + b * B + c * C;
  return [[A / det, -(b * i - c * h) / det, (b * f - c * e) / det],
          [B / det, (a * i - c * g) / det, -(a * f - c * d) / det],
          [C / det, -(a * h - b * g) / det, (a * e - b * d) / det]];
}

function toTable(px) {
  const m = invert3(tableToPixel);
  const v = [0, 1, 2].map((r) => m[r][0] * px[0] + m[r][1] * px[1] + m[r][2]);
  return [v[0] / v[2], v[1] / v[2]];
}

function imagePoint(ev) {
  const box = $("drag").getBoundingClientRect();
  return [(ev.clientX - box.left) / box.width * imageSize[0], (ev.clientY - box.top) / box.height * imageSize[1]];
}

let dragFrom = null;
const drag = $("drag");
drag.onpointerdown = (ev) => { if (tableToPixel) { dragFrom = imagePoint(ev); drag.setPointerCapture(ev.pointerId); } };
drag.onpointermove = (ev) => {
  const g = drag.getContext("2d");
  drag.width = imageSize[0]; drag.height = imageSize[1];
  if (!dragFrom) return;
  const to = imagePoint(ev);
  g.strokeStyle = "#ff80ff"; g.lineWidth = 3;
  g.beginPath(); g.moveTo(...dragFrom); g.lineTo(...to); g.stroke();
};
drag.onpointerup = (ev) => {
  if (!dragFrom) return;
  const to = imagePoint(ev);
  const a = toTable(dragFrom), b = toTable(to);
  const moved = Math.hypot(to[0] - dragFrom[0], to[1] - dragFrom[1]) > 8;
  const theta = moved ? Math.atan2(b[1] - a[1], b[0] - a[0]) : enteredThetaRad();
  dragFrom = null;
  drag.getContext("2d").clearRect(0, 0, drag.width, drag.height);
  $("mode-select").value = "move";
  $("in-x").value = a[0].toFixed(4); $("in-y").value = a[1].toFixed(4); $("in-t").value = (theta * 180 / Math.PI).toFixed(1);
  showEnteredThetaRad();
  act("PUT", "/api/v1/setpoint", { mode: "move", x_m: a[0], y_m: a[1], theta_rad: theta });
};

// -- hwsim's ground truth over the video (sim mode) -------------------------------------------------

function toPixel(x, y) {
  const m = tableToPixel;
  const v = [0, 1, 2].map((r) => m[r][0] * x + m[r][1] * y + m[r][2]);
  return [v[0] / v[2], v[1] / v[2]];
}

async function drawTruth() {
  const canvas = $("truth");
  canvas.width = imageSize[0]; canvas.height = imageSize[1];
  if (!$("show-truth").checked || !tableToPixel) return;
  try {
    const t = await call("GET", "/api/v1/sim/truth");
    const g = canvas.getContext("2d");
    g.fillStyle = "#ffeb3b";
    for (const row of t.nodes_m) for (const [x, y] of row) { const [u, v] = toPixel(x, y); g.fillRect(u - 1, v - 1, 2, 2); }
  } catch (e) { /* the toggle stays; the next poll tries again */ }
}

fetch("/api/v1/sim/truth").then((r) => { if (r.ok) $("truth-toggle").hidden = false; });
setInterval(drawTruth, 200);

call("GET", "/api/v1/camera").then((c) => { tableToPixel = c.table_to_pixel; imageSize = [c.width, c.height]; });
// A daemon with a token: asked for now, not found out when the E-STOP is pressed.
call("GET", "/api/v1/access").then((a) => {
  if (a.token_required && !token) {
    $("token-box").hidden = false;
    say("This daemon needs its API token for every change, the E-STOP too: enter it here.", true);
  }
});
connect();
