// The dashboard's view of one read data frame: its N x N cells as read (white 1, dark 0), with
// the cells whose bits the Reed-Solomon code corrected marked red; and what the camera sees of
// the cells while it cannot lock.

export const TESTED_PX_PER_CELL = 4; // the smallest cells the receiver's tests read (px per side)

export function unpackBits(b64, count) {
  // numpy.packbits's order: most significant bit first.
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  return Array.from({ length: count }, (_, i) => (bytes[i >> 3] >> (7 - (i & 7))) & 1);
}

export function drawCells(canvas, report) {
  const n = report.cells;
  const bits = unpackBits(report.bits_b64, n * n);
  const corrected = report.corrected_b64 ? unpackBits(report.corrected_b64, n * n) : null;
  const ctx = canvas.getContext("2d");
  const { width: w, height: h } = canvas;
  const cell = Math.min(w, h) / n;
  ctx.clearRect(0, 0, w, h);
  for (let i = 0; i < n * n; i++) {
    const [x, y] = [(i % n) * cell, Math.floor(i / n) * cell];
    ctx.fillStyle = corrected?.[i] ? "#ff5a5a" : bits[i] ? "#e6e8ee" : "#1b1e27";
    ctx.fillRect(x, y, cell - (cell > 4 ? 1 : 0), cell - (cell > 4 ? 1 : 0));
  }
  return corrected ? corrected.reduce((a, b) => a + b, 0) : null;
}

export function describeCells(report, correctedCount) {
  const what = `frame #${report.frame_index}, ${report.cells}x${report.cells} cells`;
  if (correctedCount == null) return `${what}: not decoded on its own (too many errors, or paper: no per-frame code)`;
  return `${what}: decoded, ${correctedCount} cell${correctedCount === 1 ? "" : "s"} corrected (red)`;
}

export function describeSight(health) {
  // "camera sees ~X px per cell" and, while not locked, why detection fails.
  const px = health.px_per_cell;
  const parts = [px == null ? "no marker seen yet" : `camera sees ~${px.toFixed(1)} px per cell`];
  const small = px != null && px < TESTED_PX_PER_CELL;
  if (small) {
    parts.push(`fewer than the ${TESTED_PX_PER_CELL} px per cell the receiver is tested at: move closer or send fewer cells`);
  }
  if (health.detection_failure) parts.push(`cannot lock: ${health.detection_failure}`);
  return { text: parts.join("; "), warn: small || Boolean(health.detection_failure) };
}
