// The dashboard's 6-DoF views: the camera's frustum, the marker and the recent trail in 3-D on a
// plain canvas (a pinhole projection from an orbiting viewpoint: drag to turn it), and the
// orientation as roll/pitch/yaw and quaternion. Poses are T_world_cam in the marker frame:
// the marker spans x, y in [0, side] at z = 0 (x right, y down), the camera sits at z < 0.

export const TENTATIVE = "#f0a04b"; // poses before a frame proved the lock
export const VERIFIED = "#5fb3ff";

const FRUSTUM = [0.62, 0.46]; // half-width, half-height per unit depth (a 4:3 camera, ~64° wide)

export function rotationMatrix([x, y, z, w]) {
  // Rows of R (camera axes are its columns) from a unit quaternion (x, y, z, w).
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ];
}

export function rollPitchYaw(q) {
  // Z-Y-X (yaw about z, then pitch about y, then roll about x), in degrees.
  const R = rotationMatrix(q);
  const deg = 180 / Math.PI;
  const pitch = Math.asin(Math.max(-1, Math.min(1, -R[2][0])));
  return [Math.atan2(R[2][1], R[2][2]) * deg, pitch * deg, Math.atan2(R[1][0], R[0][0]) * deg];
}

const sub = (a, b) => a.map((v, i) => v - b[i]);
const add = (a, b) => a.map((v, i) => v + b[i]);
const scale = (a, s) => a.map((v) => v * s);
const dot = (a, b) => a.reduce((sum, v, i) => sum + v * b[i], 0);
const cross = ([a, b, c], [d, e, f]) => [b * f - c * e, c * d - a * f, a * e - b * d];
const unit = (a) => scale(a, 1 / Math.hypot(...a));

export const orbit = { azimuth: 0.6, elevation: 0.35 }; // radians, changed by dragging

export function enableOrbit(canvas, redraw) {
  let last = null;
  canvas.addEventListener("pointerdown", (e) => {
    last = [e.clientX, e.clientY];
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointerup", () => (last = null));
  canvas.addEventListener("pointermove", (e) => {
    if (!last) return;
    orbit.azimuth += (e.clientX - last[0]) * 0.01;
    orbit.elevation = Math.max(-1.4, Math.min(1.4, orbit.elevation + (e.clientY - last[1]) * 0.01));
    last = [e.clientX, e.clientY];
    redraw();
  });
}

function viewpoint(center, distance, width, height) {
  // A pinhole looking at ``center`` from ``distance`` away; the marker's -y is up on screen.
  const { azimuth: az, elevation: el } = orbit;
  const back = [Math.sin(az) * Math.cos(el), -Math.sin(el), -Math.cos(az) * Math.cos(el)];
  const eye = add(center, scale(back, distance));
  const forward = scale(back, -1);
  const right = unit(cross(forward, [0, -1, 0]));
  const up = cross(right, forward);
  const focal = 0.9 * Math.min(width, height);
  return (p) => {
    const d = sub(p, eye);
    const z = Math.max(dot(d, forward), 1e-3);
    return [width / 2 + (focal * dot(d, right)) / z, height / 2 - (focal * dot(d, up)) / z];
  };
}

export function drawScene(canvas, poses, side) {
  // poses: [{p: [x, y, z], q: [x, y, z, w], verified}], newest last.
  const ctx = canvas.getContext("2d");
  const { width: w, height: h } = canvas;
  ctx.clearRect(0, 0, w, h);
  const markerCentre = [side / 2, side / 2, 0];
  const last = poses.at(-1);
  const reach = Math.max(side, ...poses.map((pose) => Math.hypot(...sub(pose.p, markerCentre))));
  const center = last ? scale(add(markerCentre, last.p), 0.5) : markerCentre;
  const depth = 0.3 * Math.max(side, 0.5 * reach);
  const seen = [[0, 0, 0], [side, side, 0], ...poses.map((pose) => pose.p)];
  if (last) seen.push(...frustumCorners(last, depth));
  const at = fitted(viewpoint(center, 1.5 * reach + side, w, h), seen, w, h);

  drawMarker(ctx, at, side);
  drawTrail(ctx, at, poses);
  if (last) drawFrustum(ctx, at, last, depth);
}

function fitted(project, points, width, height) {
  // Zoom the projection so that the marker, the trail and the frustum fill the canvas.
  const xy = points.map(project);
  const [xs, ys] = [xy.map((p) => p[0]), xy.map((p) => p[1])];
  const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const zoom = 0.85 * Math.min(width / Math.max(x1 - x0, 1), height / Math.max(y1 - y0, 1));
  const [cx, cy] = [(x0 + x1) / 2, (y0 + y1) / 2];
  return (p) => {
    const [x, y] = project(p);
    return [width / 2 + (x - cx) * zoom, height / 2 + (y - cy) * zoom];
  };
}

function frustumCorners(pose, depth) {
  // The far rectangle of the camera's view pyramid, in the marker frame.
  const R = rotationMatrix(pose.q);
  const [sx, sy] = FRUSTUM;
  return [[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]].map(([x, y]) =>
    add(pose.p, R.map((row) => dot(row, [x * depth, y * depth, depth]))),
  );
}

function drawMarker(ctx, at, side) {
  const corners = [[0, 0, 0], [side, 0, 0], [side, side, 0], [0, side, 0]].map(at);
  ctx.fillStyle = "rgba(230, 232, 238, 0.18)";
  ctx.strokeStyle = "#e6e8ee";
  ctx.lineWidth = 2;
  ctx.beginPath();
  corners.forEach((c, i) => (i ? ctx.lineTo(...c) : ctx.moveTo(...c)));
  ctx.closePath();
  ctx.fill();
  ctx.stroke();
  // The marker frame's axes: x red, y green, z (into the screen) blue.
  const axes = [["#ff6b6b", [side / 2, 0, 0]], ["#6bd68a", [0, side / 2, 0]], ["#6b8cff", [0, 0, side / 2]]];
  ctx.lineWidth = 1.5;
  for (const [colour, tip] of axes) {
    ctx.strokeStyle = colour;
    segment(ctx, at([0, 0, 0]), at(tip));
  }
}

function drawTrail(ctx, at, poses) {
  ctx.lineWidth = 1.5;
  for (let i = 1; i < poses.length; i++) {
    const verified = poses[i].verified;
    ctx.strokeStyle = verified ? VERIFIED : TENTATIVE;
    ctx.setLineDash(verified ? [] : [4, 3]);
    segment(ctx, at(poses[i - 1].p), at(poses[i].p));
  }
  ctx.setLineDash([]);
}

function drawFrustum(ctx, at, pose, depth) {
  const R = rotationMatrix(pose.q);
  const toWorld = (c) => add(pose.p, R.map((row) => dot(row, c)));
  const sy = FRUSTUM[1];
  const corners = frustumCorners(pose, depth).map(at);
  const apex = at(pose.p);
  ctx.strokeStyle = pose.verified ? VERIFIED : TENTATIVE;
  ctx.lineWidth = 2;
  ctx.setLineDash(pose.verified ? [] : [6, 4]);
  for (const c of corners) segment(ctx, apex, c);
  ctx.beginPath();
  corners.forEach((c, i) => (i ? ctx.lineTo(...c) : ctx.moveTo(...c)));
  ctx.closePath();
  ctx.stroke();
  ctx.setLineDash([]);
  // The image's up side (camera -y), so a roll shows.
  segment(ctx, at(toWorld([0, -sy * depth, depth])), at(toWorld([0, -1.5 * sy * depth, depth])));
  ctx.fillStyle = ctx.strokeStyle;
  ctx.beginPath();
  ctx.arc(apex[0], apex[1], 4, 0, 2 * Math.PI);
  ctx.fill();
}

function segment(ctx, a, b) {
  ctx.beginPath();
  ctx.moveTo(...a);
  ctx.lineTo(...b);
  ctx.stroke();
}
