"""The viewer page: one HTML document with its script inline (nothing loaded from the network).

Rendering is Canvas 2D: each frame projects the splats with a pinhole camera (OpenCV axes, as the
package), orders them back to front with a counting sort on quantized depth (linear time, so 300k
splats stay interactive), and alpha-blends a Gaussian footprint of each (two standard deviations
wide) into a float buffer, then applies forced alpha blending (colour divided by accumulated alpha
wherever alpha >= tau, as the renderer does; tau null = plain compositing). Controls: drag to orbit, shift-drag or right-drag to pan, wheel to zoom,
R to reset. When the first frame is drawn, `document.body.dataset.state` becomes "ready" and
`data-splats` holds the number of splats drawn, which tests read.
"""

PAGE = r"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>surfsplat viewer</title>
<style>
  html, body { margin: 0; height: 100%; background: #1e1e1e; color: #ddd; font: 13px sans-serif; overflow: hidden; }
  #view { display: block; width: 100vw; height: 100vh; cursor: grab; }
  #status { position: fixed; left: 8px; top: 6px; background: rgba(0,0,0,0.45); padding: 3px 7px; border-radius: 3px; }
  #help { position: fixed; left: 8px; bottom: 6px; color: #999; }
</style>
</head>
<body data-state="loading">
<canvas id="view"></canvas>
<div id="status">loading splats...</div>
<div id="help">drag: orbit &middot; shift-drag / right-drag: pan &middot; wheel: zoom &middot; R: reset</div>
<script>
"use strict";
const canvas = document.getElementById("view");
const ctx = canvas.getContext("2d");
const statusBox = document.getElementById("status");
const FLOATS = 8;      // x y z r g b opacity radius
const BINS = 4096;     // depth buckets of the counting sort
let meta = null, splats = null, cam = null, home = null, dirty = true, drawing = false;

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
function rotate(v, axis, angle) {  // Rodrigues
  const k = norm(axis), c = Math.cos(angle), s = Math.sin(angle);
  return add(add(mul(v, c), mul(cross(k, v), s)), mul(k, dot(k, v) * (1 - c)));
}
function basis(c) {  // OpenCV camera axes: x right, y down, z forward
  const forward = norm(sub(c.target, c.position));
  const down = norm(sub(mul(c.up, -1), mul(forward, dot(mul(c.up, -1), forward))));
  return { forward, down, right: cross(down, forward) };
}

function resize() {
  const w = Math.max(1, Math.floor(canvas.clientWidth)), h = Math.max(1, Math.floor(canvas.clientHeight));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; dirty = true; }
}

function draw() {
  if (!splats) return;
  resize();
  const W = canvas.width, H = canvas.height, n = meta.count;
  const t0 = performance.now();
  const { forward, down, right } = basis(cam);
  const f = (H / 2) / Math.tan((cam.fov_deg * Math.PI / 180) / 2);
  const px = new Float32Array(n), py = new Float32Array(n), pz = new Float32Array(n), pr = new Float32Array(n);
  let zmin = Infinity, zmax = -Infinity, visible = 0;
  const e = cam.position;
  for (let i = 0; i < n; i++) {
    const o = i * FLOATS;
    const dx = splats[o] - e[0], dy = splats[o + 1] - e[1], dz = splats[o + 2] - e[2];
    const z = dx * forward[0] + dy * forward[1] + dz * forward[2];
    if (z <= 1e-6) { pz[i] = -1; continue; }
    const u = f * (dx * right[0] + dy * right[1] + dz * right[2]) / z + W / 2;
    const v = f * (dx * down[0] + dy * down[1] + dz * down[2]) / z + H / 2;
    const r = Math.min(24, Math.max(0.7, 2 * f * splats[o + 7] / z));
    if (u < -r || v < -r || u > W + r || v > H + r) { pz[i] = -1; continue; }
    px[i] = u; py[i] = v; pz[i] = z; pr[i] = r; visible++;
    if (z < zmin) zmin = z;
    if (z > zmax) zmax = z;
  }
  // Counting sort on quantized depth, far to near.
  const count = new Uint32Array(BINS + 1), bin = new Uint16Array(n);
  const scale = (BINS - 1) / Math.max(zmax - zmin, 1e-9);
  for (let i = 0; i < n; i++) {
    if (pz[i] < 0) continue;
    const b = BINS - 1 - Math.floor((pz[i] - zmin) * scale);
    bin[i] = b; count[b + 1]++;
  }
  for (let b = 0; b < BINS; b++) count[b + 1] += count[b];
  const order = new Uint32Array(visible);
  for (let i = 0; i < n; i++) if (pz[i] >= 0) order[count[bin[i]]++] = i;

  // Composite on zero, then apply forced alpha blending (paper Sec. 3.4) as the renderer does:
  // colour / alpha wherever alpha >= tau (such pixels count as opaque), background elsewhere.
  const rgb = new Float32Array(W * H * 3), acc = new Float32Array(W * H);
  for (let k = 0; k < visible; k++) {
    const i = order[k], o = i * FLOATS;
    const u = px[i], v = py[i], r = pr[i], inv = 2 / (r * r), op = splats[o + 6];
    const cr = splats[o + 3], cg = splats[o + 4], cb = splats[o + 5];
    const x0 = Math.max(0, Math.floor(u - r)), x1 = Math.min(W - 1, Math.ceil(u + r));
    const y0 = Math.max(0, Math.floor(v - r)), y1 = Math.min(H - 1, Math.ceil(v + r));
    for (let y = y0; y <= y1; y++) {
      const ddy = y + 0.5 - v;
      for (let x = x0; x <= x1; x++) {
        const ddx = x + 0.5 - u;
        const a = op * Math.exp(-(ddx * ddx + ddy * ddy) * inv);
        if (a < 1 / 255) continue;
        const q = y * W + x, p = q * 3;
        rgb[p] += a * (cr - rgb[p]); rgb[p + 1] += a * (cg - rgb[p + 1]); rgb[p + 2] += a * (cb - rgb[p + 2]);
        acc[q] += a * (1 - acc[q]);
      }
    }
  }
  const image = ctx.createImageData(W, H), tau = meta.alpha_threshold, bg = 0.118;
  for (let k = 0; k < W * H; k++) {
    const p = k * 3, a = acc[k];
    let r, g, b;
    if (tau !== null && a >= tau) { r = rgb[p] / a; g = rgb[p + 1] / a; b = rgb[p + 2] / a; }
    else if (tau !== null) { r = g = b = bg; }
    else { r = rgb[p] + (1 - a) * bg; g = rgb[p + 1] + (1 - a) * bg; b = rgb[p + 2] + (1 - a) * bg; }
    image.data[4 * k] = r * 255; image.data[4 * k + 1] = g * 255; image.data[4 * k + 2] = b * 255; image.data[4 * k + 3] = 255;
  }
  ctx.putImageData(image, 0, 0);
  const ms = performance.now() - t0;
  statusBox.textContent = `${meta.title}: ${visible.toLocaleString()} of ${meta.count.toLocaleString()} splats drawn` +
    (meta.total > meta.count ? ` (subsampled from ${meta.total.toLocaleString()})` : "") + `, ${ms.toFixed(0)} ms`;
  document.body.dataset.splats = String(visible);
  document.body.dataset.state = "ready";
}

function frame() {
  if (dirty && !drawing) { drawing = true; dirty = false; draw(); drawing = false; }
  requestAnimationFrame(frame);
}

let drag = null;
canvas.addEventListener("contextmenu", (ev) => ev.preventDefault());
canvas.addEventListener("mousedown", (ev) => { drag = { x: ev.clientX, y: ev.clientY, pan: ev.shiftKey || ev.button === 2 }; });
window.addEventListener("mouseup", () => { drag = null; });
window.addEventListener("mousemove", (ev) => {
  if (!drag || !cam) return;
  const dx = ev.clientX - drag.x, dy = ev.clientY - drag.y;
  drag.x = ev.clientX; drag.y = ev.clientY;
  const { forward, down, right } = basis(cam);
  if (drag.pan) {
    const s = Math.hypot(...sub(cam.target, cam.position)) / canvas.height;
    const shift = add(mul(right, -dx * s), mul(down, -dy * s));
    cam.position = add(cam.position, shift); cam.target = add(cam.target, shift);
  } else {
    let offset = sub(cam.position, cam.target);
    offset = rotate(offset, cam.up, -dx * 0.005);
    offset = rotate(offset, right, dy * 0.005);
    cam.position = add(cam.target, offset);
  }
  dirty = true;
});
canvas.addEventListener("wheel", (ev) => {
  ev.preventDefault();
  if (!cam) return;
  const offset = mul(sub(cam.position, cam.target), Math.exp(ev.deltaY * 0.001));
  cam.position = add(cam.target, offset); dirty = true;
}, { passive: false });
window.addEventListener("keydown", (ev) => { if (ev.key === "r" || ev.key === "R") { cam = JSON.parse(JSON.stringify(home)); dirty = true; } });
window.addEventListener("resize", () => { dirty = true; });

async function main() {
  try {
    meta = await (await fetch("meta.json")).json();
    const buffer = await (await fetch("splats.bin")).arrayBuffer();
    splats = new Float32Array(buffer);
    if (splats.length !== meta.count * FLOATS) throw new Error(`splats.bin holds ${splats.length} floats, expected ${meta.count * FLOATS}`);
    document.title = `${meta.title} - surfsplat viewer`;
    home = meta.camera; cam = JSON.parse(JSON.stringify(home));
    draw();  // the first frame at once (animation frames may be throttled in background or headless tabs)
    requestAnimationFrame(frame);
  } catch (err) {
    statusBox.textContent = "error: " + err.message;
    document.body.dataset.state = "error";
  }
}
main();
</script>
</body>
</html>
"""
