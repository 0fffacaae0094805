"""A single self-contained HTML page that shows the Gaussians: the splats embedded, a WebGL2
splat renderer inline, nothing fetched (it opens from disk, offline, in any browser with WebGL2).

Embedded data (base64 in a <script type="application/octet-stream"> element), column after
column, 17 bytes a Gaussian, little-endian:

    quats   N × 4 bytes  SOG's "smallest three" (export/sog.py): the three smaller components of the
                         unit (w, x, y, z) times sign(largest)·√2 as 255·(c/2 + ½), then 252 + the
                         largest's index
    rgba    N × 4 bytes  colour 0.5 + C0·f_dc and alpha sigmoid(opacity), ×255 (degree-0 colour only)
    means   N × 3 uint16 position in the box config.lo .. config.hi, 65535 steps an axis
    scales  N × 3 bytes  log scale in config.slo .. config.shi, 255 steps

and a JSON config (count, boxes, camera, up axis, background). The page decodes it, builds each
Gaussian's 3-D covariance, and draws one screen-aligned quad per Gaussian (EWA projection with
the model's dilation, the Jacobian clamped as in 3DGS, 3σ), sorted back to front by a 16-bit
counting sort of the view depth whenever the camera moves, blended with premultiplied alpha over
the background.

Controls: drag to orbit the target (or, in first-person mode, to look around), right- or
shift-drag to pan, wheel to zoom (first-person: move), W/A/S/D or arrows to move, Q/E down/up,
F to switch orbit/first-person, R to reset the camera. `#hud=0` hides the help line.
"""

from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path

import numpy as np

__all__ = ["html_page", "write_html", "read_html_splats", "default_camera", "BACKGROUND"]

#: The page's background (sRGB bytes).
BACKGROUND = (24, 24, 28)


def _np(t) -> np.ndarray:
    return t.detach().to("cpu").double().numpy()


def _byte(x) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def splat_payload(g) -> tuple[bytes, dict]:
    """The embedded bytes and the part of the config that decodes them."""
    from gaussians.model import SH_C0

    n = len(g)
    means = _np(g.means)
    if n == 0 or not np.all(np.isfinite(means)):
        raise ValueError("the page needs at least one Gaussian, all positions finite")
    lo, hi = means.min(0), means.max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    pos = np.rint((means - lo) / span * 65535.0).clip(0, 65535).astype("<u2")
    ls = _np(g.log_scales)
    slo, shi = float(ls.min()), float(ls.max())
    sspan = shi - slo if shi > slo else 1.0
    scales = _byte((ls - slo) / sspan * 255.0)
    rgb = 0.5 + SH_C0 * _np(g.sh_dc).reshape(n, 3)
    alpha = 1.0 / (1.0 + np.exp(-_np(g.opacity_logits)))
    rgba = _byte(np.concatenate([rgb, alpha[:, None]], 1) * 255.0)
    from export.sog import pack_quats

    data = b"".join([pack_quats(_np(g.quats)).tobytes(), rgba.tobytes(), pos.tobytes(), scales.tobytes()])
    cfg = {"count": n, "lo": lo.tolist(), "hi": hi.tolist(), "slo": slo, "shi": shi,
           "eps2d": float(getattr(g, "eps2d", 0.3))}
    return data, cfg


def default_camera(means: np.ndarray, up=(0.0, -1.0, 0.0), fovy_deg: float = 60.0) -> dict:
    """An orbit camera looking at the middle of the splats' box along the horizontal axis of the
    world's forward (+z for y down, −z for y up), far enough back to see the whole box."""
    m = np.asarray(means, dtype=np.float64)
    lo, hi = np.percentile(m, 2, axis=0), np.percentile(m, 98, axis=0)
    if len(m) < 50:
        lo, hi = m.min(0), m.max(0)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    fwd = np.array([0.0, 0.0, 1.0 if up[1] < 0 else -1.0])
    dist = radius / math.tan(math.radians(fovy_deg) / 2) * 1.1
    return {"eye": (centre - fwd * dist).tolist(), "target": centre.tolist(), "mode": "orbit",
            "fovy": fovy_deg}


def html_page(g, camera: dict | None = None, up=(0.0, -1.0, 0.0), title: str = "pano-pipe splats",
              background=BACKGROUND) -> str:
    """The page for the Gaussians `g`. `camera`: {"eye", "target", "mode": "orbit"|"walk", "fovy"}
    (default: `default_camera`); `up`: the world's up axis (pano-pipe's world is y down)."""
    data, cfg = splat_payload(g)
    cam = dict(camera) if camera else default_camera(_np(g.means), up)
    cam.setdefault("fovy", 60.0)
    cam.setdefault("mode", "orbit")
    cfg.update(camera=cam, up=[float(u) for u in up], background=[int(b) for b in background],
               speed=float(max(np.linalg.norm(np.subtract(cfg["hi"], cfg["lo"])) * 0.15, 0.05)))
    b64 = base64.b64encode(data).decode("ascii")
    bg = "rgb({},{},{})".format(*cfg["background"])
    return (_PAGE.replace("__TITLE__", html.escape(title)).replace("__BG__", bg)
            .replace("__CONFIG__", json.dumps(cfg, separators=(",", ":")).replace("</", "<\\/"))
            .replace("__DATA__", b64).replace("__SCRIPT__", _SCRIPT))


def write_html(path: str | Path, g, **kw) -> Path:
    path = Path(path)
    path.write_text(html_page(g, **kw), encoding="utf-8")
    return path


def read_html_splats(path: str | Path) -> dict[str, np.ndarray]:
    """Decode the splats a page embeds, as the page does: means, log_scales, rgb, alpha in [0,1],
    unit (w,x,y,z) quats, and the config."""
    import re

    from export.sog import unpack_quats

    text = Path(path).read_text(encoding="utf-8")
    cfg = json.loads(re.search(r'<script type="application/json" id="config">(.*?)</script>', text, re.S)
                     .group(1).replace("<\\/", "</"))
    raw = base64.b64decode(re.search(r'<script type="application/octet-stream" id="splats">(.*?)</script>',
                                     text, re.S).group(1))
    n = cfg["count"]
    if len(raw) != 17 * n:
        raise ValueError(f"{path}: {len(raw)} bytes of splats, expected {17 * n}")
    q = np.frombuffer(raw, np.uint8, 4 * n, 0).reshape(n, 4)
    rgba = np.frombuffer(raw, np.uint8, 4 * n, 4 * n).reshape(n, 4) / 255.0
    pos = np.frombuffer(raw, "<u2", 3 * n, 8 * n).reshape(n, 3).astype(np.float64)
    sc = np.frombuffer(raw, np.uint8, 3 * n, 14 * n).reshape(n, 3).astype(np.float64)
    lo, hi = np.asarray(cfg["lo"]), np.asarray(cfg["hi"])
    span = np.where(hi > lo, hi - lo, 1.0)
    sspan = cfg["shi"] - cfg["slo"] if cfg["shi"] > cfg["slo"] else 1.0
    return {"means": lo + pos / 65535.0 * span, "log_scales": cfg["slo"] + sc / 255.0 * sspan,
            "rgb": rgba[:, :3], "alpha": rgba[:, 3], "quats": unpack_quats(q), "config": cfg}


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>__TITLE__</title>
<style>
html, body { margin: 0; height: 100%; overflow: hidden; background: __BG__; }
canvas { display: block; width: 100vw; height: 100vh; touch-action: none; }
#hud { position: fixed; left: 8px; bottom: 8px; font: 12px/1.4 system-ui, sans-serif; color: #ccc;
       background: rgba(0,0,0,0.45); padding: 4px 8px; border-radius: 4px; user-select: none; }
#hud button { font: inherit; margin-right: 6px; }
#msg { position: fixed; top: 40%; width: 100%; text-align: center; color: #eee;
       font: 16px system-ui, sans-serif; }
</style>
</head>
<body>
<canvas id="c"></canvas>
<div id="hud"><button id="mode">orbit</button><span id="help"></span></div>
<div id="msg"></div>
<script type="application/json" id="config">__CONFIG__</script>
<script type="application/octet-stream" id="splats">__DATA__</script>
<script>
__SCRIPT__
</script>
</body>
</html>
"""

_SCRIPT = r"""
"use strict";
(function () {
const cfg = JSON.parse(document.getElementById("config").textContent);
const canvas = document.getElementById("c");
const msg = document.getElementById("msg");
if (/hud=0/.test(location.hash + location.search)) document.getElementById("hud").style.display = "none";
window.splatFrames = 0;
const gl = canvas.getContext("webgl2", {antialias: false, alpha: false, preserveDrawingBuffer: true});
if (!gl) { msg.textContent = "This page needs WebGL2."; window.splatError = "no webgl2"; return; }

// ---- decode the embedded splats
const N = cfg.count;
const b64 = document.getElementById("splats").textContent.trim();
const bin = atob(b64);
const raw = new Uint8Array(bin.length);
for (let i = 0; i < bin.length; i++) raw[i] = bin.charCodeAt(i);
const quat = raw.subarray(0, 4 * N), rgba = raw.subarray(4 * N, 8 * N);
const pos = new Uint16Array(raw.buffer, 8 * N, 3 * N), scl = raw.subarray(14 * N, 17 * N);
const lo = cfg.lo, hi = cfg.hi;
const span = [0, 1, 2].map(a => (hi[a] > lo[a] ? hi[a] - lo[a] : 1) / 65535);
const sspan = (cfg.shi > cfg.slo ? cfg.shi - cfg.slo : 1) / 255;
const ROW = 1024;                       // splats a texture row; 4 RGBA32F texels a splat
const rows = Math.max(1, Math.ceil(N / ROW));
const tex = new Float32Array(ROW * 4 * rows * 4);
const centres = new Float32Array(3 * N);
const SQ2 = Math.SQRT2, ORDER = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]];
const q = [0, 0, 0, 0];
for (let i = 0; i < N; i++) {
  const x = lo[0] + pos[3 * i] * span[0], y = lo[1] + pos[3 * i + 1] * span[1];
  const z = lo[2] + pos[3 * i + 2] * span[2];
  centres[3 * i] = x; centres[3 * i + 1] = y; centres[3 * i + 2] = z;
  const big = quat[4 * i + 3] - 252, o = ORDER[big & 3];
  let ss = 0;
  for (let k = 0; k < 3; k++) { const v = (quat[4 * i + k] / 255 * 2 - 1) / SQ2; q[o[k]] = v; ss += v * v; }
  q[big & 3] = Math.sqrt(Math.max(0, 1 - ss));
  const [w, qx, qy, qz] = q;
  const R = [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy),
             2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx),
             2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)];
  const s = [0, 1, 2].map(a => Math.exp(cfg.slo + scl[3 * i + a] * sspan));
  const M = [];                          // M = R diag(s); covariance M Mᵀ
  for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) M.push(R[3 * r + c] * s[c]);
  const cov = (a, b) => M[3 * a] * M[3 * b] + M[3 * a + 1] * M[3 * b + 1] + M[3 * a + 2] * M[3 * b + 2];
  const t = ((i / ROW | 0) * ROW * 4 + (i % ROW) * 4) * 4;
  tex.set([x, y, z, 1, cov(0, 0), cov(0, 1), cov(0, 2), 0, cov(1, 1), cov(1, 2), cov(2, 2), 0,
           rgba[4 * i] / 255, rgba[4 * i + 1] / 255, rgba[4 * i + 2] / 255, rgba[4 * i + 3] / 255], t);
}

// ---- GL
const VS = `#version 300 es
precision highp float; precision highp int;
uniform highp sampler2D uData;
uniform vec3 uEye, uR, uD, uF;
uniform vec2 uViewport;
uniform float uFocal, uEps;
in vec2 aCorner; in uint aIndex;
out vec4 vColor; out vec2 vPos;
void main() {
  int i = int(aIndex);
  ivec2 b = ivec2((i % ${ROW}) * 4, i / ${ROW});
  vec4 t0 = texelFetch(uData, b, 0), t1 = texelFetch(uData, b + ivec2(1, 0), 0);
  vec4 t2 = texelFetch(uData, b + ivec2(2, 0), 0), t3 = texelFetch(uData, b + ivec2(3, 0), 0);
  vec3 p = t0.xyz - uEye;
  vec3 c = vec3(dot(uR, p), dot(uD, p), dot(uF, p));      // camera frame: x right, y down, z ahead
  if (c.z < 0.02) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  mat3 S = mat3(t1.x, t1.y, t1.z, t1.y, t2.x, t2.y, t1.z, t2.y, t2.z);
  mat3 W = transpose(mat3(uR, uD, uF));
  mat3 Sc = W * S * transpose(W);
  float iz = 1.0 / c.z;
  // as 3DGS: the Jacobian at the centre clamped to 1.3× the half field of view (bounded footprints
  // for splats beside the camera; the centre itself is not moved)
  vec2 lim = 1.3 * 0.5 * uViewport / uFocal;
  vec2 m = clamp(c.xy * iz, -lim, lim);
  vec3 j1 = vec3(uFocal * iz, 0.0, -uFocal * m.x * iz);
  vec3 j2 = vec3(0.0, uFocal * iz, -uFocal * m.y * iz);
  float a = dot(j1, Sc * j1) + uEps, bb = dot(j1, Sc * j2), d = dot(j2, Sc * j2) + uEps;
  float mid = 0.5 * (a + d), rad = length(vec2(0.5 * (a - d), bb));
  float l1 = min(mid + rad, 1.6e7), l2 = clamp(mid - rad, 1e-4, 1.6e7);
  vec2 e1 = abs(bb) > 1e-12 ? normalize(vec2(bb, l1 - a)) : (a >= d ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 e2 = vec2(-e1.y, e1.x);
  vec2 px = uFocal * c.xy * iz + 3.0 * (aCorner.x * sqrt(l1) * e1 + aCorner.y * sqrt(l2) * e2);
  gl_Position = vec4(2.0 * px.x / uViewport.x, -2.0 * px.y / uViewport.y, 0.0, 1.0);
  vPos = 3.0 * aCorner;
  vColor = t3;
}`;
const FS = `#version 300 es
precision highp float;
in vec4 vColor; in vec2 vPos; out vec4 outColor;
void main() {
  float r2 = dot(vPos, vPos);
  if (r2 > 9.0) discard;
  float a = vColor.a * exp(-0.5 * r2);
  if (a < 1.0 / 255.0) discard;
  outColor = vec4(vColor.rgb * a, a);
}`;
function shader(type, src) {
  const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}
const prog = gl.createProgram();
gl.attachShader(prog, shader(gl.VERTEX_SHADER, VS)); gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, FS));
gl.linkProgram(prog);
if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
gl.useProgram(prog);
const U = {};
for (const n of ["uData", "uEye", "uR", "uD", "uF", "uViewport", "uFocal", "uEps"]) {
  U[n] = gl.getUniformLocation(prog, n);
}
const texture = gl.createTexture();
gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, texture);
gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, ROW * 4, rows, 0, gl.RGBA, gl.FLOAT, tex);
gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
gl.uniform1i(U.uData, 0);
gl.uniform1f(U.uEps, cfg.eps2d);
const vao = gl.createVertexArray(); gl.bindVertexArray(vao);
const quad = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, quad);
gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
const aCorner = gl.getAttribLocation(prog, "aCorner");
gl.enableVertexAttribArray(aCorner); gl.vertexAttribPointer(aCorner, 2, gl.FLOAT, false, 0, 0);
const order = new Uint32Array(N);
const indexBuf = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, indexBuf);
gl.bufferData(gl.ARRAY_BUFFER, order.byteLength, gl.DYNAMIC_DRAW);
const aIndex = gl.getAttribLocation(prog, "aIndex");
gl.enableVertexAttribArray(aIndex); gl.vertexAttribIPointer(aIndex, 1, gl.UNSIGNED_INT, 0, 0);
gl.vertexAttribDivisor(aIndex, 1);
gl.disable(gl.DEPTH_TEST); gl.enable(gl.BLEND);
gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
const bg = cfg.background.map(v => v / 255);

// ---- camera: yaw/pitch about the world's up axis, around a target at a distance
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b, k = 1) => [a[0] + k * b[0], a[1] + k * b[1], a[2] + k * b[2]];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = a => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
const UP = norm(cfg.up), DOWN = [-UP[0], -UP[1], -UP[2]];
let F0 = Math.abs(UP[2]) < 0.9 ? [0, 0, 1] : [1, 0, 0];
F0 = norm(add(F0, UP, -dot(F0, UP)));
const R0 = norm(cross(DOWN, F0));
let cam;
function reset() {
  const c = cfg.camera, f = norm(sub(c.target, c.eye));
  cam = {target: c.target.slice(), dist: Math.max(1e-3, Math.hypot(...sub(c.target, c.eye))),
         pitch: Math.asin(Math.max(-1, Math.min(1, dot(f, UP)))), yaw: Math.atan2(dot(f, R0), dot(f, F0)),
         mode: c.mode === "walk" ? "walk" : "orbit"};
  document.getElementById("mode").textContent = cam.mode === "walk" ? "first-person" : "orbit";
  dirty = true;
}
function basis() {
  const cp = Math.cos(cam.pitch), sp = Math.sin(cam.pitch);
  const cy = cp * Math.cos(cam.yaw), sy = cp * Math.sin(cam.yaw);
  const f = norm([0, 1, 2].map(a => cy * F0[a] + sy * R0[a] + sp * UP[a]));
  const r = norm(cross(DOWN, f));
  return {f, r, d: cross(f, r), eye: add(cam.target, f, -cam.dist)};
}
let dirty = true, sortedFor = null;
const depth = new Float32Array(N), counts = new Uint32Array(65536), keys = new Uint16Array(N);
function sort(eye, f) {
  let mn = Infinity, mx = -Infinity;
  for (let i = 0; i < N; i++) {
    const v = (centres[3 * i] - eye[0]) * f[0] + (centres[3 * i + 1] - eye[1]) * f[1]
            + (centres[3 * i + 2] - eye[2]) * f[2];
    depth[i] = v; if (v < mn) mn = v; if (v > mx) mx = v;
  }
  const k = mx > mn ? 65535 / (mx - mn) : 0;
  counts.fill(0);
  for (let i = 0; i < N; i++) { const b = 65535 - ((depth[i] - mn) * k | 0); keys[i] = b; counts[b]++; }
  for (let b = 1; b < 65536; b++) counts[b] += counts[b - 1];   // far first: key 0 is the farthest
  for (let i = N - 1; i >= 0; i--) order[--counts[keys[i]]] = i;
  gl.bindBuffer(gl.ARRAY_BUFFER, indexBuf); gl.bufferSubData(gl.ARRAY_BUFFER, 0, order);
}
function draw() {
  const w = Math.max(1, Math.round(canvas.clientWidth * devicePixelRatio));
  const h = Math.max(1, Math.round(canvas.clientHeight * devicePixelRatio));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  const B = basis();
  const key = B.eye.concat(B.f).join(",");
  if (key !== sortedFor) { sort(B.eye, B.f); sortedFor = key; }
  gl.viewport(0, 0, w, h);
  gl.clearColor(bg[0], bg[1], bg[2], 1); gl.clear(gl.COLOR_BUFFER_BIT);
  gl.uniform3fv(U.uEye, B.eye); gl.uniform3fv(U.uR, B.r); gl.uniform3fv(U.uD, B.d); gl.uniform3fv(U.uF, B.f);
  gl.uniform2f(U.uViewport, w, h);
  gl.uniform1f(U.uFocal, h / 2 / Math.tan(cfg.camera.fovy * Math.PI / 360));
  gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, N);
  window.splatFrames++;
}

// ---- input
const keysDown = new Set();
let drag = null;
canvas.addEventListener("contextmenu", e => e.preventDefault());
canvas.addEventListener("pointerdown", e => {
  canvas.setPointerCapture(e.pointerId);
  drag = {x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey};
});
canvas.addEventListener("pointerup", () => { drag = null; });
canvas.addEventListener("pointermove", e => {
  if (!drag) return;
  const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
  drag.x = e.clientX; drag.y = e.clientY;
  if (drag.pan) {
    const B = basis(), k = cam.dist * 2 * Math.tan(cfg.camera.fovy * Math.PI / 360) / canvas.clientHeight;
    cam.target = add(add(cam.target, B.r, -dx * k), B.d, -dy * k);
  } else {
    const eye = basis().eye, s = cam.mode === "walk" ? -0.004 : 0.006;
    cam.yaw += dx * s; cam.pitch = Math.max(-1.55, Math.min(1.55, cam.pitch - dy * s));
    if (cam.mode === "walk") cam.target = add(eye, basis().f, cam.dist);  // turn the head, stay put
  }
  dirty = true;
});
canvas.addEventListener("wheel", e => {
  e.preventDefault();
  if (cam.mode === "walk") cam.target = add(cam.target, basis().f, -Math.sign(e.deltaY) * cfg.speed * 0.5);
  else cam.dist = Math.max(0.02, cam.dist * Math.exp(e.deltaY * 0.001));
  dirty = true;
}, {passive: false});
function toggle() {
  cam.mode = cam.mode === "walk" ? "orbit" : "walk";
  if (cam.mode === "walk") { const B = basis(); cam.dist = 0.5; cam.target = add(B.eye, B.f, 0.5); }
  document.getElementById("mode").textContent = cam.mode === "walk" ? "first-person" : "orbit";
  dirty = true;
}
document.getElementById("mode").addEventListener("click", toggle);
window.addEventListener("keydown", e => {
  const k = e.key.toLowerCase();
  if (k === "f") toggle(); else if (k === "r") reset(); else keysDown.add(k);
});
window.addEventListener("keyup", e => keysDown.delete(e.key.toLowerCase()));
window.addEventListener("blur", () => keysDown.clear());
window.addEventListener("resize", () => { dirty = true; });
document.getElementById("help").textContent =
  "drag: orbit / look · right- or shift-drag: pan · wheel: zoom · WASD/arrows, Q/E: move · " +
  "F: first-person · R: reset";
let last = performance.now();
function frame(now) {
  const dt = Math.min(0.1, (now - last) / 1000); last = now;
  if (keysDown.size) {
    const B = basis(), v = cfg.speed * dt;
    let m = [0, 0, 0];
    if (keysDown.has("w") || keysDown.has("arrowup")) m = add(m, B.f, v);
    if (keysDown.has("s") || keysDown.has("arrowdown")) m = add(m, B.f, -v);
    if (keysDown.has("d") || keysDown.has("arrowright")) m = add(m, B.r, v);
    if (keysDown.has("a") || keysDown.has("arrowleft")) m = add(m, B.r, -v);
    if (keysDown.has("e")) m = add(m, UP, v);
    if (keysDown.has("q")) m = add(m, UP, -v);
    if (m[0] || m[1] || m[2]) { cam.target = add(cam.target, m); dirty = true; }
  }
  if (dirty) { dirty = false; draw(); }
  requestAnimationFrame(frame);
}
reset();
draw(); dirty = false;
window.splatReady = true;
requestAnimationFrame(frame);
})();
"""
