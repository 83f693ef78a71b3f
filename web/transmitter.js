// Transmitter page: plays a message as the dynamic marker, exactly one frame per display refresh.
//
// Frames come from GET /api/messages/{id}/frames in packed-bit batches, fetched well ahead so
// the network never holds up the display. If a frame is still missing when its refresh comes,
// the previous frame stays up and the index does not advance (a "stall"): frames are never
// skipped. Query options: id, profile, cells, cell_px (0 = fit the screen), mode (fixed or
// auto), capture=N (keep the pixels of the first N frames drawn, for tests, in
// window.eventocc.captured).
//
// Auto mode: the server chooses profile, cells and how many refreshes each frame is held for,
// from what the receivers measure, and says so in the answer to every status report. Each
// choice starts a new segment of packed frames (fixed-size fountain symbols, the same at every
// density) from the next symbol the last segment did not send, so a receiver keeps what it
// collected of the message across the change.

const BATCH = 60; // frames per request
const BUFFER_SECONDS = 3; // keep this much fetched ahead of the display
const MAX_IN_FLIGHT = 2;
const RETRY_AFTER_MS = 2000; // after a failed fetch, instead of retrying on every refresh
const METER_WINDOW = 240; // refresh intervals in the running median
const MISSED_FACTOR = 1.5; // an interval this much over the median missed a refresh
const STATUS_EVERY_MS = 1000;
const AUTO_STATUS_EVERY_MS = 250; // auto: the answer carries the server's choice
const DRAWN_HISTORY = 600;

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);

const settings = {
  id: params.get("id"),
  profile: params.get("profile"),
  cells: intParam("cells"),
  cellPx: intParam("cell_px") ?? 0,
  mode: params.get("mode"), // null: whatever the server holds
};
// What is on screen: the user's settings in fixed mode, the server's choice in auto.
const segment = { packed: false, profile: null, cells: null, hold: 1, symbolStart: 0 };
const captureLimit = intParam("capture") ?? 0;

// What tests and the status report read: never reassigned, only updated.
const eventocc = {
  frameIndex: 0,
  playing: false,
  acknowledged: false,
  refreshHz: null,
  missedRefreshes: 0,
  stalls: 0,
  link: null, // the server's last word on the mode: {mode, choice, reason, ...}
  segments: 0, // auto segments started
  drawn: [], // ring of the last DRAWN_HISTORY frame indices drawn, oldest first
  captured: [], // {frameIndex, x, y, width, height, rgba: Uint8ClampedArray}
  capturedBase64,
  setPlaying, // for automation: setPlaying(false) holds the frame on screen
};
window.eventocc = eventocc;

function intParam(name) {
  const value = params.get(name);
  return value === null || value === "" ? null : Number.parseInt(value, 10);
}

// --- API ---------------------------------------------------------------------------------
const token = () => sessionStorage.getItem("eventocc-token");

async function api(path, options = {}) {
  const headers = new Headers(options.headers);
  if (token()) headers.set("Authorization", `Bearer ${token()}`);
  const response = await fetch(path, { ...options, headers });
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    const detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail);
    const error = new Error(detail || `${response.status} ${response.statusText}`);
    error.status = response.status;
    throw error;
  }
  return response;
}

// --- frames, fetched ahead in batches ----------------------------------------------------
class FrameBuffer {
  constructor(id, profile, cells, packed = false, symbolStart = 0) {
    this.query = new URLSearchParams({ count: BATCH, profile, cells });
    if (packed) {
      this.query.set("packed", "true");
      this.query.set("symbol_start", symbolStart);
    }
    this.symbolsPerFrame = null; // from X-Frame-Symbols
    this.path = `/api/messages/${encodeURIComponent(id)}/frames`;
    this.batches = new Map(); // first frame index -> {side, frameBytes, bits}
    this.inFlight = new Set();
    this.retryAt = 0;
    this.side = null;
  }

  /** Packed bits of frame k, or null if not fetched yet. */
  get(k) {
    const batch = this.batches.get(k - (k % BATCH));
    if (!batch) return null;
    const offset = (k % BATCH) * batch.frameBytes;
    return batch.bits.subarray(offset, offset + batch.frameBytes);
  }

  /** Fetch what is missing in [k, k + ahead) and drop batches already shown. */
  fill(k, ahead) {
    for (const start of this.batches.keys()) if (start + BATCH <= k) this.batches.delete(start);
    if (performance.now() < this.retryAt) return;
    for (let start = k - (k % BATCH); start < k + ahead; start += BATCH) {
      if (this.inFlight.size >= MAX_IN_FLIGHT) return;
      if (!this.batches.has(start) && !this.inFlight.has(start)) this.fetch(start);
    }
  }

  async fetch(start) {
    this.inFlight.add(start);
    this.query.set("start", start);
    try {
      const response = await api(`${this.path}?${this.query}`);
      const side = Number(response.headers.get("X-Frame-Side"));
      const frameBytes = Number(response.headers.get("X-Frame-Bytes"));
      this.symbolsPerFrame = Number(response.headers.get("X-Frame-Symbols")) || 1;
      const bits = new Uint8Array(await response.arrayBuffer());
      this.side = side;
      this.batches.set(start, { side, frameBytes, bits });
    } catch (error) {
      this.retryAt = performance.now() + RETRY_AFTER_MS;
      showError(`frames ${start}+: ${error.message}`);
    } finally {
      this.inFlight.delete(start);
    }
  }
}

// --- refresh-rate meter ------------------------------------------------------------------
class RefreshMeter {
  constructor() {
    this.intervals = [];
    this.last = null;
  }

  /** Record one refresh at `now` (ms); true if the interval before it missed a refresh. */
  tick(now) {
    const interval = this.last === null ? null : now - this.last;
    this.last = now;
    if (interval === null) return false;
    const median = this.median();
    this.intervals.push(interval);
    if (this.intervals.length > METER_WINDOW) this.intervals.shift();
    return median !== null && interval > MISSED_FACTOR * median;
  }

  median() {
    if (this.intervals.length < 10) return null;
    const sorted = [...this.intervals].sort((a, b) => a - b);
    return sorted[sorted.length >> 1];
  }

  reset() {
    this.last = null;
  }
}

// --- drawing -----------------------------------------------------------------------------
const canvas = $("marker");
const ctx = canvas.getContext("2d", { alpha: false });
const cellCanvas = document.createElement("canvas"); // one pixel per cell, scaled up on draw
const cellCtx = cellCanvas.getContext("2d");
let cellImage = null;
let placement = null; // {x, y, size, cellPx} in device pixels

function resizeCanvas() {
  const dpr = window.devicePixelRatio || 1;
  canvas.width = Math.round(window.innerWidth * dpr);
  canvas.height = Math.round(window.innerHeight * dpr);
  placement = null;
  clearCanvas();
}

function clearCanvas() {
  ctx.fillStyle = "#000";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
}

/** Integer cell size and position centring a side x side marker on the canvas. */
function place(side) {
  const fit = Math.floor((0.9 * Math.min(canvas.width, canvas.height)) / side);
  const cellPx = settings.cellPx > 0 ? settings.cellPx : Math.max(1, fit);
  const size = side * cellPx;
  return {
    side, cellPx, size,
    x: Math.floor((canvas.width - size) / 2),
    y: Math.floor((canvas.height - size) / 2),
  };
}

function draw(bits, side) {
  if (!placement || placement.side !== side) {
    clearCanvas();
    placement = place(side);
    cellCanvas.width = cellCanvas.height = side;
    cellImage = cellCtx.createImageData(side, side);
  }
  const rgba = cellImage.data;
  for (let i = 0, n = side * side; i < n; i++) {
    const value = (bits[i >> 3] >> (7 - (i & 7))) & 1 ? 255 : 0; // MSB first, 1 = white
    const o = i << 2;
    rgba[o] = rgba[o + 1] = rgba[o + 2] = value;
    rgba[o + 3] = 255;
  }
  cellCtx.putImageData(cellImage, 0, 0);
  ctx.imageSmoothingEnabled = false; // nearest neighbour: every cell an exact cellPx square
  ctx.drawImage(cellCanvas, placement.x, placement.y, placement.size, placement.size);
}

function capture(frameIndex) {
  const { x, y, size } = placement;
  const rgba = ctx.getImageData(x, y, size, size).data;
  eventocc.captured.push({ frameIndex, x, y, width: size, height: size, rgba });
}

function capturedBase64() {
  return eventocc.captured.map(({ rgba, ...rest }) => {
    let binary = "";
    for (let i = 0; i < rgba.length; i += 0x8000) {
      binary += String.fromCharCode(...rgba.subarray(i, i + 0x8000));
    }
    return { ...rest, rgba: btoa(binary) };
  });
}

// --- the display loop --------------------------------------------------------------------
const meter = new RefreshMeter();
let frames = null; // FrameBuffer of the message being sent
let messages = []; // as listed by the API
let heldFor = 0; // refreshes the frame on screen has been up (auto may hold each for several)

function onRefresh(now) {
  const missed = meter.tick(now);
  const median = meter.median();
  eventocc.refreshHz = median ? 1000 / median : null;
  if (eventocc.playing && frames) {
    if (missed) eventocc.missedRefreshes++;
    const bits = frames.get(eventocc.frameIndex);
    if (bits && heldFor > 0) {
      heldFor++; // the same frame stays up for this refresh
    } else if (bits) {
      draw(bits, frames.side);
      if (eventocc.captured.length < captureLimit) capture(eventocc.frameIndex);
      eventocc.drawn.push(eventocc.frameIndex);
      if (eventocc.drawn.length > DRAWN_HISTORY) eventocc.drawn.shift();
      heldFor = 1;
    } else {
      eventocc.stalls++;
    }
    if (heldFor >= segment.hold) {
      heldFor = 0;
      eventocc.frameIndex++;
    }
  }
  if (frames) frames.fill(eventocc.frameIndex, aheadFrames());
  requestAnimationFrame(onRefresh);
}

function aheadFrames() {
  return Math.ceil(BUFFER_SECONDS * (eventocc.refreshHz ?? 60));
}

function bufferedSeconds() {
  if (!frames || !eventocc.refreshHz) return 0;
  let k = eventocc.frameIndex;
  while (frames.get(k)) k += BATCH - (k % BATCH);
  return (k - eventocc.frameIndex) / eventocc.refreshHz;
}

function setPlaying(playing) {
  if (playing && (!eventocc.acknowledged || !frames)) return;
  eventocc.playing = playing;
  meter.reset(); // the pause itself is not a missed refresh
  if (playing) document.activeElement?.blur(); // let the control panel fade out
  document.body.classList.toggle("playing", playing);
  $("play").textContent = playing ? "Pause" : "Start";
  reportStatus(); // at once: a camera watching this screen must not wait for the next report
  updateOverlay();
}

// Changing what is sent restarts the stream at frame 0.
function restartStream() {
  setPlaying(false);
  eventocc.frameIndex = 0;
  heldFor = 0;
  Object.assign(segment, {
    packed: false, profile: settings.profile, cells: settings.cells, hold: 1, symbolStart: 0,
  });
  frames = settings.id ? new FrameBuffer(settings.id, settings.profile, settings.cells) : null;
  placement = null;
  clearCanvas();
  $("play").disabled = !frames || !eventocc.acknowledged;
  const url = new URL(location.href);
  for (const [key, value] of [["id", settings.id], ["profile", settings.profile],
    ["cells", settings.cells], ["cell_px", settings.cellPx], ["mode", settings.mode]]) {
    if (value === null || value === "") url.searchParams.delete(key);
    else url.searchParams.set(key, value);
  }
  history.replaceState(null, "", url);
}

// --- auto mode: the server's choice ------------------------------------------------------------
function sameChoice(choice) {
  return segment.packed && segment.profile === choice.profile && segment.cells === choice.cells
    && segment.hold === choice.hold;
}

// Answers may come back out of order (a status report and a mode change in flight at once):
// only the latest request's answer counts.
let linkAsked = 0;
let linkApplied = 0;

/** Take the server's word on the mode: in auto, start a segment of its choice if it differs. */
function applyLink(link, asked) {
  if (!link || asked < linkApplied) return;
  linkApplied = asked;
  eventocc.link = link;
  $("mode").value = link.mode;
  document.body.classList.toggle("auto", link.mode === "auto");
  $("auto-reason").hidden = link.mode !== "auto";
  $("profile").disabled = $("cells").disabled = link.mode === "auto"; // the server chooses
  $("auto-reason").textContent = link.mode === "auto" && link.choice
    ? `auto: ${link.choice.profile}, ${link.choice.cells} cells, ${link.choice.frame_hz.toFixed(0)} Hz — ${link.reason}`
    : "";
  if (link.mode === "auto" && link.choice && frames && !sameChoice(link.choice)) {
    startSegment(link.choice);
  } else if (link.mode === "fixed" && segment.packed) {
    const playing = eventocc.playing;
    restartStream(); // back to the user's own settings
    if (playing) setPlaying(true);
  }
}

// A new packed segment goes on from the next symbol the last one did not send: every frame
// shown carried symbolsPerFrame symbols (a blank frame's share is skipped, which costs
// nothing: the fountain needs any symbols, not these ones).
function startSegment(choice) {
  const symbolStart = segment.packed
    ? segment.symbolStart + eventocc.frameIndex * (frames.symbolsPerFrame ?? 1)
    : 0;
  Object.assign(segment, {
    packed: true, profile: choice.profile, cells: choice.cells, hold: choice.hold, symbolStart,
  });
  frames = new FrameBuffer(settings.id, choice.profile, choice.cells, true, symbolStart);
  eventocc.frameIndex = 0;
  eventocc.segments++;
  heldFor = 0;
  placement = null;
  $("profile").value = choice.profile;
  $("cells").value = choice.cells;
  setTimeout(reportStatus, 0); // the cameras must hear of it at once
}

async function setMode(mode) {
  settings.mode = mode;
  const asked = ++linkAsked;
  try {
    const response = await api("/api/transmitter/mode", {
      method: "PUT",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ mode }),
    });
    applyLink(await response.json(), asked);
    showError("");
  } catch (error) {
    showError(`mode: ${error.message}`);
  }
}

// --- overlay and status report -------------------------------------------------------------
function updateOverlay() {
  const hz = eventocc.refreshHz ? `${eventocc.refreshHz.toFixed(1)} Hz` : "– Hz";
  const parts = [
    eventocc.playing ? "playing" : "paused",
    hz,
    `frame ${eventocc.frameIndex}`,
    `missed ${eventocc.missedRefreshes}`,
    `stalls ${eventocc.stalls}`,
    `buffer ${bufferedSeconds().toFixed(1)} s`,
  ];
  $("stats").textContent = parts.join("  ·  ");
  $("state-dot").classList.toggle("on", eventocc.playing);
}

async function reportStatus() {
  updateOverlay();
  const report = {
    message_id: settings.id,
    profile: segment.profile ?? settings.profile,
    cells: segment.cells ?? settings.cells,
    cell_px: placement?.cellPx ?? null,
    playing: eventocc.playing,
    frame_index: eventocc.frameIndex,
    // The rate frames change at, which receivers are built for; the server multiplies it
    // back by the hold for the display's own.
    refresh_hz: eventocc.refreshHz && eventocc.refreshHz / segment.hold,
    packed: segment.packed,
    symbol_start: segment.symbolStart,
    hold: segment.hold,
    missed_refreshes: eventocc.missedRefreshes,
    stalls: eventocc.stalls,
    user_agent: navigator.userAgent.slice(0, 512),
  };
  const asked = ++linkAsked;
  try {
    const response = await api("/api/transmitter/status", {
      method: "POST",
      keepalive: true, // sent even as the page closes (closing hides it, which pauses it)
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(report),
    });
    applyLink((await response.json()).link, asked);
  } catch {
    // The display must go on even when the server is briefly unreachable.
  }
}

// --- controls ------------------------------------------------------------------------------
function showError(text) {
  $("error").textContent = text;
  $("error").hidden = !text;
}

function describe(m) {
  const size = m.size < 1024 ? `${m.size} B` : `${(m.size / 1024).toFixed(1)} KiB`;
  return `${m.name} · ${size} · ${m.profile}/${m.cells}`;
}

function showFacts(m) {
  if (!m) {
    $("facts").textContent = "Upload a message to start.";
    return;
  }
  const kbps = (m.bit_rate_60hz / 1000).toFixed(1);
  const loop = `${m.frames_per_loop} frames per loop`;
  $("facts").textContent = `${m.bits_per_frame} bits/frame · ${kbps} kbit/s at 60 Hz · ${loop}`;
}

async function loadMessages(selectId) {
  ({ messages } = await (await api("/api/messages")).json());
  const select = $("message");
  select.replaceChildren(...messages.map((m) => new Option(describe(m), m.id)));
  // No id: the newest. An id the server does not hold plays nothing, rather than another
  // message the camera would then be taken to receive.
  const chosen = selectId ? messages.find((m) => m.id === selectId) : messages[0];
  select.value = chosen?.id ?? "";
  if (selectId && !chosen) showError(`no message ${selectId} on this server: choose one above`);
  return chosen;
}

function chooseMessage(message, keepOptions) {
  settings.id = message?.id ?? null;
  if (message && !keepOptions) {
    settings.profile = message.profile;
    settings.cells = message.cells;
  }
  $("profile").value = settings.profile ?? "";
  $("cells").value = settings.cells ?? "";
  showFacts(message);
  restartStream();
}

async function upload(file) {
  const body = new FormData();
  body.append("file", file);
  const query = new URLSearchParams({ profile: $("profile").value, cells: $("cells").value });
  try {
    const response = await api(`/api/messages?${query}`, { method: "POST", body });
    const created = await response.json();
    await loadMessages(created.id);
    chooseMessage(created, false);
    showError("");
  } catch (error) {
    if (error.status === 401) {
      $("token").hidden = false;
      $("token").focus();
    }
    showError(`upload failed: ${error.message}`);
  }
}

function toggleFullscreen() {
  if (document.fullscreenElement) document.exitFullscreen();
  else document.documentElement.requestFullscreen().catch((e) => showError(e.message));
}

function bindControls() {
  $("message").addEventListener("change", (e) => {
    chooseMessage(messages.find((m) => m.id === e.target.value), false);
  });
  $("profile").addEventListener("change", (e) => {
    settings.profile = e.target.value;
    restartStream();
  });
  $("cells").addEventListener("change", (e) => {
    settings.cells = Number.parseInt(e.target.value, 10);
    restartStream();
  });
  $("cell-px").addEventListener("change", (e) => {
    settings.cellPx = Math.max(0, Number.parseInt(e.target.value, 10) || 0);
    placement = null;
    clearCanvas();
  });
  $("upload").addEventListener("change", (e) => {
    if (e.target.files.length) upload(e.target.files[0]);
    e.target.value = "";
  });
  $("token").addEventListener("change", (e) => sessionStorage.setItem("eventocc-token", e.target.value));
  $("play").addEventListener("click", () => setPlaying(!eventocc.playing));
  $("mode").addEventListener("change", (e) => setMode(e.target.value));
  $("fullscreen").addEventListener("click", toggleFullscreen);
  $("controls").addEventListener("submit", (e) => e.preventDefault());

  document.addEventListener("keydown", (e) => {
    if (e.target.closest("input, select, textarea") || e.ctrlKey || e.metaKey || e.altKey) return;
    if (e.key === " ") setPlaying(!eventocc.playing);
    else if (e.key === "f") toggleFullscreen();
    else if (e.key === "h") document.body.classList.toggle("bare");
    else return;
    e.preventDefault();
  });
  // A hidden tab gets no refreshes: pause rather than count the gap as missed frames.
  document.addEventListener("visibilitychange", () => {
    if (document.hidden) setPlaying(false);
  });
  window.addEventListener("resize", resizeCanvas);
}

function askAcknowledgement() {
  const dialog = $("warning");
  dialog.addEventListener("cancel", (e) => e.preventDefault()); // Esc does not dismiss it
  dialog.addEventListener("close", () => {
    eventocc.acknowledged = true;
    $("play").disabled = !frames;
  });
  dialog.showModal();
}

async function main() {
  resizeCanvas();
  askAcknowledgement();
  const [{ profiles, default_profile, default_cells, min_cells, max_cells }, chosen] =
    await Promise.all([api("/api/profiles").then((r) => r.json()), loadMessages(settings.id)]);
  $("profile").replaceChildren(...profiles.map((p) => new Option(p, p)));
  Object.assign($("cells"), { min: min_cells, max: max_cells });
  $("cell-px").value = settings.cellPx;
  bindControls();

  const keepOptions = settings.profile !== null || settings.cells !== null;
  settings.profile ??= chosen?.profile ?? default_profile;
  settings.cells ??= chosen?.cells ?? default_cells;
  chooseMessage(chosen, keepOptions);
  if (settings.mode) await setMode(settings.mode);
  else {
    const asked = ++linkAsked;
    applyLink(await (await api("/api/transmitter/mode")).json(), asked);
  }
  statusLoop();
  requestAnimationFrame(onRefresh);
}

function statusLoop() {
  reportStatus();
  setTimeout(statusLoop, eventocc.link?.mode === "auto" ? AUTO_STATUS_EVERY_MS : STATUS_EVERY_MS);
}

main().catch((error) => showError(error.message));
