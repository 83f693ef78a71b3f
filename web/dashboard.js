// The live dashboard: one websocket (/ws/dashboard) feeds a small state object; a
// requestAnimationFrame loop redraws only what changed. Reconnects with backoff and says so.

import { describeCells, describeSight, drawCells } from "./cells_view.js";
import { drawScene, enableOrbit, rollPitchYaw } from "./pose_view.js";

const MARKER_SIDE_M = 0.272; // the receiver's default marker size, for scale in the 2D views
const TRAIL = 600; // poses kept for the trajectory (6 s at the 100 Hz the daemon publishes)
const SERIES = 120; // one sample per second in each sparkline
const RECONNECT_S = [0.5, 8];
const GOODPUT_WINDOW_MS = 60_000; // messages completed: as the server's /metrics gauge
const VERIFIED_WINDOW_MS = 10_000; // verified frame payload: the link's live rate
const KEEPING_UP = 0.95; // source speed (x real time) below which the source is behind
const PROGRESS_STALE_MS = 10_000; // a stream's progress not reported for this long is dropped
const LAG_WINDOW_MS = 10_000; // poses whose arrival lag the pose latency is measured over

const $ = (id) => document.getElementById(id);

const state = {
  poses: [], // {t, p: [x, y, z], q: [x, y, z, w], axis: [x, y, z], verified}, newest last
  arrivals: [], // [ms, lag ms] per pose: its arrival less its event time (another clock)
  cells: null, // the latest read frame's cells report
  linkMode: null, // the server's transmitter mode and choice (link_mode updates)
  posesThisSecond: 0,
  progress: new Map(), // "receiver:stream_id" -> {report, firstSeen: [ms, held], seen: ms}
  receptions: new Map(), // id -> reception
  recentBits: [], // [ms, bits] of receptions this page saw arrive, for goodput
  verifiedBits: [], // [ms, bits] of frame payload that passed its CRC, for goodput
  lastFrame: null,
  health: null,
  series: { goodput: [], ber: [], events: [], poses: [] },
  dirty: new Set(["pose", "messages", "charts"]),
};

// Exposed for tests and curious users: read-only by convention.
window.eventoccDashboard = state;

// --- the connection --------------------------------------------------------------------------
let retryS = RECONNECT_S[0];

function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const socket = new WebSocket(`${scheme}://${location.host}/ws/dashboard`);
  socket.onopen = () => {
    retryS = RECONNECT_S[0];
    showConnection("live", "live");
    loadReceptions();
  };
  socket.onmessage = (event) => handle(JSON.parse(event.data));
  socket.onclose = () => {
    showConnection("down", `server unreachable: reconnecting in ${retryS.toFixed(1)} s`);
    setTimeout(connect, retryS * 1000);
    retryS = Math.min(retryS * 2, RECONNECT_S[1]);
  };
}

function showConnection(kind, text) {
  const pill = $("connection");
  pill.dataset.state = kind;
  pill.textContent = text;
}

async function loadReceptions() {
  try {
    const response = await fetch("/api/receptions");
    for (const r of (await response.json()).receptions) state.receptions.set(r.id, r);
    state.dirty.add("messages");
  } catch {
    // the websocket's close handler already says the server is away
  }
}

// --- updates ---------------------------------------------------------------------------------
const handlers = {
  pose(u) {
    trackPose(u);
    state.dirty.add("pose");
  },
  cells(u) {
    state.cells = u;
    state.dirty.add("cells");
  },
  frame(u) {
    state.lastFrame = u;
    if (u.payload_bits) state.verifiedBits.push([performance.now(), u.payload_bits]);
    state.dirty.add("state");
  },
  health(u) {
    state.health = u;
    state.dirty.add("state");
  },
  progress(u) {
    trackProgress(u);
    state.dirty.add("messages");
  },
  reception(u) {
    state.receptions.set(u.id, u);
    state.recentBits.push([performance.now(), 8 * u.size]);
    endProgress(u);
    state.dirty.add("messages");
  },
  surface(u) {
    drawSurface(u);
  },
  receivers(u) {
    const ids = u.receivers.map((r) => r.receiver);
    $("receivers").textContent = ids.length ? `receivers: ${ids.join(", ")}` : "no receiver connected";
  },
  link_mode(u) {
    state.linkMode = u;
    state.dirty.add("adapt");
  },
  transmitter(u) {
    const hz = u.refresh_hz ? `${u.refresh_hz.toFixed(1)} Hz` : "– Hz";
    const what = u.message_id ? `${u.message_id} ${u.profile}/${u.cells}` : "no message";
    $("transmitter").textContent = `${u.playing ? "playing" : "paused"} ${what}, ${hz}, frame ${u.frame_index}`;
    $("missed").textContent = `${u.missed_refreshes} missed, ${u.stalls} stalls`;
  },
};

function handle(update) {
  handlers[update.type]?.(update);
}

// --- poses -----------------------------------------------------------------------------------
function trackPose(u) {
  const q = u.quaternion_xyzw;
  state.poses.push({ t: u.t_us, p: u.position, q, axis: opticalAxis(q), verified: u.verified ?? false });
  if (state.poses.length > TRAIL) state.poses.splice(0, state.poses.length - TRAIL);
  state.posesThisSecond += 1;
  // Event time runs on the receiver's clock: only its lag beyond the quickest recent pose says
  // how late a pose arrives (what the network and the server add, and the receiver's backlog).
  const now = performance.now();
  state.arrivals.push([now, now - u.t_us / 1000]);
  while (state.arrivals[0][0] < now - LAG_WINDOW_MS) state.arrivals.shift();
}

function poseLagMs() {
  const lags = state.arrivals.map(([, lag]) => lag);
  return lags.length ? lags.at(-1) - Math.min(...lags) : null;
}

function drawPose3d() {
  drawScene($("scene-view"), state.poses, MARKER_SIDE_M);
  const last = state.poses.at(-1);
  if (!last) return;
  const [roll, pitch, yaw] = rollPitchYaw(last.q);
  const deg = (v) => `${v >= 0 ? "+" : ""}${v.toFixed(1)}°`;
  $("orientation").textContent = `roll ${deg(roll)}  pitch ${deg(pitch)}  yaw ${deg(yaw)}`;
  $("quaternion").textContent = `q (x y z w) ${last.q.map((v) => v.toFixed(3)).join(" ")}`;
  const status = $("pose-status");
  status.dataset.state = last.verified ? "verified" : "tentative";
  status.textContent = last.verified ? "verified" : "tentative: no frame has proven the lock yet";
  const lag = poseLagMs();
  $("pose-lag").textContent = lag == null ? "–" : `${lag.toFixed(0)} ms behind the quickest pose of the last 10 s`;
}

function drawCellsView() {
  const corrected = drawCells($("cells-view"), state.cells);
  $("cells-caption").textContent = describeCells(state.cells, corrected);
}

function drawSight() {
  const sight = describeSight(state.health);
  const dd = $("sight");
  dd.textContent = sight.text;
  dd.dataset.state = sight.warn ? "behind" : "live";
}

// --- message progress ------------------------------------------------------------------------
// Keyed by receiver and stream id: a stream's progress has no name until its metadata decoded,
// and two receivers may read the same stream.
const progressKey = (u) => `${u.receiver}:${u.stream_id}`;

function trackProgress(u) {
  const known = state.progress.get(progressKey(u));
  const firstSeen = known ? known.firstSeen : [performance.now(), u.symbols_held];
  state.progress.set(progressKey(u), { report: u, firstSeen, seen: performance.now() });
}

function endProgress(reception) {
  // The server names the stream a finished message came in (receptions loaded over REST do not:
  // they finished before this page opened).
  if (reception.stream_id != null) state.progress.delete(progressKey(reception));
}

function dropStaleProgress() {
  // A stream the receiver stopped reporting (the transmitter moved on to another message).
  const since = performance.now() - PROGRESS_STALE_MS;
  for (const [key, p] of state.progress) if (p.seen < since) state.progress.delete(key);
}

function opticalAxis([x, y, z, w]) {
  // Third column of the rotation matrix: where the camera looks, in the marker frame.
  return [2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)];
}

// --- drawing ---------------------------------------------------------------------------------
function drawViews() {
  drawPose3d();
  // top: (x, z) with z growing down the canvas; side: (z, y), y down.
  drawView($("top-view"), (v) => [v[0], v[2]], [[0, 0], [MARKER_SIDE_M, 0]]);
  drawView($("side-view"), (v) => [v[2], v[1]], [[0, 0], [0, MARKER_SIDE_M]]);
  const last = state.poses.at(-1);
  if (last) {
    const [x, y, z] = last.p;
    const d = Math.hypot(x - MARKER_SIDE_M / 2, y - MARKER_SIDE_M / 2, z);
    $("pose-readout").textContent =
      `x ${x.toFixed(3)}  y ${y.toFixed(3)}  z ${z.toFixed(3)} m   distance ${d.toFixed(2)} m`;
  }
}

function drawView(canvas, project, marker) {
  const ctx = canvas.getContext("2d");
  const { width: w, height: h } = canvas;
  ctx.clearRect(0, 0, w, h);
  const points = state.poses.map((pose) => project(pose.p));
  const all = [...marker, ...points];
  const xs = all.map((p) => p[0]);
  const ys = all.map((p) => p[1]);
  const span = Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys), 0.3);
  const scale = (0.8 * Math.min(w, h)) / span;
  const cx = (Math.max(...xs) + Math.min(...xs)) / 2;
  const cy = (Math.max(...ys) + Math.min(...ys)) / 2;
  const at = ([u, v]) => [w / 2 + (u - cx) * scale, h / 2 + (v - cy) * scale];

  ctx.lineWidth = 3;
  ctx.strokeStyle = "#e6e8ee"; // the screen
  line(ctx, at(marker[0]), at(marker[1]));
  if (!points.length) return;
  ctx.lineWidth = 1;
  ctx.strokeStyle = "rgba(95, 179, 255, 0.45)"; // the recent trajectory
  ctx.beginPath();
  points.forEach((p, i) => (i ? ctx.lineTo(...at(p)) : ctx.moveTo(...at(p))));
  ctx.stroke();
  const last = state.poses.at(-1);
  const head = at(project(last.p));
  const axis = project(last.axis);
  ctx.strokeStyle = "#5fb3ff"; // where the camera looks
  ctx.lineWidth = 2;
  line(ctx, head, [head[0] + axis[0] * 24, head[1] + axis[1] * 24]);
  ctx.fillStyle = "#5fb3ff";
  ctx.beginPath();
  ctx.arc(head[0], head[1], 5, 0, 2 * Math.PI);
  ctx.fill();
}

function line(ctx, a, b) {
  ctx.beginPath();
  ctx.moveTo(...a);
  ctx.lineTo(...b);
  ctx.stroke();
}

function drawMessages() {
  dropStaleProgress();
  const progress = $("progress");
  progress.replaceChildren(
    ...[...state.progress.values()].map(({ report: r, firstSeen: [t0, held0] }) => {
      const li = document.createElement("li");
      const share = r.symbols_needed ? Math.min(1, r.symbols_held / r.symbols_needed) : 0;
      const rate = (r.symbols_held - held0) / ((performance.now() - t0) / 1000);
      const left = r.symbols_needed - r.symbols_held;
      const eta = rate > 0 && left > 0 ? `, ETA ${(left / rate).toFixed(0)} s` : "";
      li.textContent = `${r.name ?? `stream ${r.stream_id}`}: ${r.symbols_held}/${r.symbols_needed} symbols${eta}`;
      const bar = document.createElement("div");
      bar.className = "bar";
      bar.innerHTML = `<div style="width: ${(100 * share).toFixed(1)}%"></div>`;
      li.append(bar);
      return li;
    }),
  );
  const list = $("receptions");
  const receptions = [...state.receptions.values()].sort((a, b) => (a.received < b.received ? 1 : -1));
  if (!receptions.length) return;
  list.replaceChildren(
    ...receptions.map((r) => {
      const li = document.createElement("li");
      li.dataset.sha256 = r.sha256;
      const link = document.createElement("a");
      link.href = r.url;
      link.textContent = r.name || r.id;
      link.download = r.name || r.id;
      const facts = document.createElement("span");
      // The message's own rate, not the link's goodput (every verified frame's payload, repair
      // symbols included): its bits over the time from its first symbol to its last.
      const speed = r.goodput_bps ? `, message at ${formatRate(r.goodput_bps, "bit/s")}` : "";
      // Matching an upload or the sender's in-band sha256 checks the bytes; paper sends none.
      const check = r.message_id ? "sha256 matches upload" : r.verified ? "sha256 matches sender's" : "unchecked";
      facts.className = r.message_id || r.verified ? "verified" : "muted";
      facts.textContent = `${r.size} B, ${check}${speed}`;
      facts.title = "the message's bits over the time from its first symbol to its last";
      li.append(link, facts);
      return li;
    }),
  );
}

function drawState() {
  const h = state.health;
  if (h) {
    $("cpu-load").textContent = `${(100 * h.cpu_load).toFixed(0)} % of a core`;
    showSourceSpeed(h.source_speed);
    showWaiting(h);
    showCamera(h.camera);
    drawSight();
  }
  const f = state.lastFrame;
  if (f) {
    $("frame-stats").textContent =
      `#${f.frame_index}, ${f.bits_read} bits, confidence ${f.confidence_mean.toFixed(2)}`;
  }
}

function showWaiting(h) {
  // A source with nothing to show (the transmitter page paused or closed) says why: the
  // receiver is idle, not tracking with its last pose frozen.
  $("tracking-state").textContent = h.waiting ? `idle: ${h.waiting}` : h.state;
  $("tracking-state").dataset.state = h.waiting ? "waiting" : h.state;
  if (h.waiting) $("source-speed").textContent = "no events: waiting for the screen";
}

function showSourceSpeed(speed) {
  // Only a live source reports its speed: the share of its events the receiver kept up with.
  const dd = $("source-speed");
  const behind = speed != null && speed < KEEPING_UP;
  dd.dataset.state = behind ? "behind" : "live";
  if (speed == null) dd.textContent = "live";
  else if (!behind) dd.textContent = "keeps up with real time";
  else dd.textContent = `source at ${speed.toFixed(2)}x real time: skipping ahead to stay live`;
}

function showCamera(camera) {
  // A live camera's own readings and its USB link's losses; other sources send none.
  const dd = $("camera");
  dd.dataset.state = camera?.usb_overflows ? "behind" : "live";
  if (!camera) {
    dd.textContent = "–";
    return;
  }
  const parts = [];
  if (camera.temperature_c != null) parts.push(`${camera.temperature_c.toFixed(1)} °C`);
  if (camera.illuminance != null) {
    const light = camera.illuminance.toFixed(0);
    parts.push(camera.illuminance_unit === "lux" ? `${light} lux` : `light sensor ${light}`);
  }
  parts.push(camera.max_event_rate ? `limit ${formatRate(camera.max_event_rate, "ev/s")}` : "no rate limit");
  if (camera.usb_overflows) {
    parts.push(`USB lost packets ${camera.usb_overflows}x (${(1000 * camera.usb_lost_s).toFixed(0)} ms of events)`);
  }
  dd.textContent = parts.join(", ");
}

function drawSurface(u) {
  const canvas = $("surface");
  canvas.width = u.width;
  canvas.height = u.height;
  const values = Uint8Array.from(atob(u.pixels_b64), (c) => c.charCodeAt(0));
  const image = canvas.getContext("2d").createImageData(u.width, u.height);
  values.forEach((v, i) => image.data.set([v, v, Math.min(255, v + 40), 255], 4 * i));
  canvas.getContext("2d").putImageData(image, 0, 0);
}

function sample() {
  // Once a second: one point per sparkline.
  const f = state.lastFrame;
  const push = (name, value) => {
    const s = state.series[name];
    s.push(value);
    if (s.length > SERIES) s.shift();
  };
  const rate = (name, windowMs) => {
    const since = performance.now() - windowMs;
    state[name] = state[name].filter(([t]) => t >= since);
    return state[name].reduce((sum, [, bits]) => sum + bits, 0) / (windowMs / 1000);
  };
  // The verified payload of the frames, while it still flows after the message completed;
  // the paper profile's frames carry no check, so its completed messages count instead.
  const framed = rate("verifiedBits", VERIFIED_WINDOW_MS);
  push("goodput", state.verifiedBits.length ? framed : rate("recentBits", GOODPUT_WINDOW_MS));
  push("ber", f ? (f.ber ?? 1 - f.confidence_mean) : null);
  push("events", state.health?.events_per_s ?? f?.events_per_s ?? null);
  push("poses", state.posesThisSecond);
  state.posesThisSecond = 0;
  state.dirty.add("charts");
  if (state.progress.size) state.dirty.add("messages"); // to drop the stale
}

function drawCharts() {
  const charts = {
    goodput: (v) => formatRate(v, "bit/s"),
    ber: (v) => v.toExponential(1),
    events: (v) => formatRate(v, "ev/s"),
    poses: (v) => `${v.toFixed(0)} Hz`,
  };
  for (const [name, format] of Object.entries(charts)) {
    const values = state.series[name];
    const last = values.at(-1);
    $(`${name}-value`).textContent = last == null ? "–" : format(last);
    sparkline($(`${name}-chart`), values);
  }
}

function sparkline(canvas, values) {
  const ctx = canvas.getContext("2d");
  const { width: w, height: h } = canvas;
  ctx.clearRect(0, 0, w, h);
  const known = values.filter((v) => v != null);
  if (!known.length) return;
  const top = Math.max(...known) || 1;
  ctx.strokeStyle = "#5fb3ff";
  ctx.beginPath();
  values.forEach((v, i) => {
    if (v == null) return;
    const x = (i / (SERIES - 1)) * w;
    const y = h - 2 - (v / top) * (h - 4);
    i && values[i - 1] != null ? ctx.lineTo(x, y) : ctx.moveTo(x, y);
  });
  ctx.stroke();
}

function formatRate(v, unit) {
  if (v >= 1e6) return `${(v / 1e6).toFixed(1)} M${unit}`;
  if (v >= 1e3) return `${(v / 1e3).toFixed(1)} k${unit}`;
  return `${v.toFixed(0)} ${unit}`;
}

// --- the transmitter's settings (auto mode) --------------------------------------------------
function drawAdapt() {
  const u = state.linkMode;
  if (!u) return;
  const c = u.choice;
  $("link-mode").textContent = u.mode + (u.pinned ? `, pinned to ${u.pinned}` : "");
  $("link-choice").textContent = c
    ? `${c.profile}, ${c.cells} cells, ${c.frame_hz.toFixed(0)} frames/s` + (c.hold > 1 ? ` (each held ${c.hold} refreshes)` : "")
      + `, for ${u.since_s.toFixed(0)} s`
    : "what the page's user set";
  $("link-reason").textContent = u.reason;
  $("link-served").textContent = u.served ?? "–";
  const last = u.history.at(-1);
  $("link-goodput").textContent = last ? formatRate(last.bps, "bit/s") : "–";
  drawLinkHistory($("link-history"), u.history);
}

/** Goodput a second, one bar each, with a tick and the new settings where they changed. */
function drawLinkHistory(canvas, history) {
  const ctx = canvas.getContext("2d");
  const { width: w, height: h } = canvas;
  ctx.clearRect(0, 0, w, h);
  if (!history.length) return;
  const top = Math.max(...history.map((p) => p.bps)) || 1;
  const step = w / Math.max(history.length, 60);
  ctx.font = "10px sans-serif";
  history.forEach((p, i) => {
    const x = i * step;
    const bar = (p.bps / top) * (h - 14);
    ctx.fillStyle = "#5fb3ff";
    ctx.fillRect(x, h - bar, Math.max(step - 1, 1), bar);
    if (i === 0 || history[i - 1].settings !== p.settings) {
      ctx.fillStyle = "#ffb35f";
      ctx.fillRect(x, 0, 1, h);
      ctx.fillText(p.settings, x + 2, 10);
    }
  });
}

const painters = {
  adapt: drawAdapt,
  pose: drawViews,
  messages: drawMessages,
  state: drawState,
  charts: drawCharts,
  cells: drawCellsView,
};

function frame() {
  for (const part of state.dirty) painters[part]();
  state.dirty.clear();
  requestAnimationFrame(frame);
}

connect();
enableOrbit($("scene-view"), () => state.dirty.add("pose"));
setInterval(sample, 1000);
requestAnimationFrame(frame);
