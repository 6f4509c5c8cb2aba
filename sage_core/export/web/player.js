// sage web player: plays a surfel avatar posed on the GPU from per-frame FLAME mesh vertices.
// Data: window.SAGE_AVATAR (avatar.js, written by `sage export --web`; layout in sage_core/export/web.py).
// URL query: frame=i (show frame i, paused), camera=ref (the capture's reference camera at its pixel
// size; default: an orbit camera starting there), ui=0 (hide the controls), speed=x (playback speed).
// Keys: space play / pause, R reset the view.
"use strict";
(function () {
  const doc = window.SAGE_AVATAR;
  const query = new URLSearchParams(location.search);
  const canvas = document.getElementById("view");
  const msg = document.getElementById("msg");
  const bar = document.getElementById("bar");
  const playBtn = document.getElementById("play");
  const slider = document.getElementById("slider");
  const label = document.getElementById("label");
  const speedSel = document.getElementById("speed");
  const resetBtn = document.getElementById("reset");
  const fpsLabel = document.getElementById("fps");
  window.sageReady = false;
  window.sageFps = 0;

  function fail(text) {
    msg.textContent = text;
    window.sageError = text;
  }
  if (!doc) { fail("avatar.js is missing or did not load"); return; }
  const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, premultipliedAlpha: false, preserveDrawingBuffer: true });
  if (!gl) { fail("this browser has no WebGL2"); return; }

  // ------------------------------------------------------------------ data
  const N = doc.n_surfels, V = doc.n_vertices, T = doc.n_frames;
  const raw = atob(doc.data);
  const bytes = new Uint8Array(raw.length);
  for (let i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
  const buf = bytes.buffer;
  const tri = new Uint32Array(buf, 0, N * 3);
  const mu = new Float32Array(buf, 12 * N, N * 3);
  const rot = new Float32Array(buf, 24 * N, N * 4);
  const scl = new Float32Array(buf, 40 * N, N * 2);
  const rgba = new Uint8Array(buf, 48 * N, N * 4);
  const qverts = new Int16Array(buf, 52 * N, T * V * 3);
  let off = 52 * N + 6 * T * V;
  const frameCols = doc.frame_colors ? new Uint8Array(buf, off, T * N * 3) : null;
  if (doc.frame_colors) off += T * N * 3;
  const frameDq = doc.frame_correction ? new Int8Array(buf, off, T * N * 4) : null;
  if (doc.frame_correction) off += T * N * 4;
  const frameLf = doc.frame_correction ? new Int8Array(buf, off, T * N * 2) : null;
  const vs = doc.vert_scale, vo = doc.vert_offset;

  const TW = 1024;
  function texHeight(count) { return Math.max(1, Math.ceil(count / TW)); }
  function makeTexture(internal, format, type, data, count) {
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, TW, texHeight(count), 0, format, type, data);
    return t;
  }
  const padN = TW * texHeight(N);
  const triData = new Uint32Array(padN * 4);
  const muData = new Float32Array(padN * 4);
  const rotData = new Float32Array(padN * 4);
  const colData = new Uint8Array(padN * 4);
  const s1bits = new Uint32Array(new Float32Array(scl.filter((_, i) => i % 2 === 1)).buffer);
  for (let i = 0; i < N; i++) {
    triData[4 * i] = tri[3 * i]; triData[4 * i + 1] = tri[3 * i + 1]; triData[4 * i + 2] = tri[3 * i + 2];
    triData[4 * i + 3] = s1bits[i];
    muData[4 * i] = mu[3 * i]; muData[4 * i + 1] = mu[3 * i + 1]; muData[4 * i + 2] = mu[3 * i + 2];
    muData[4 * i + 3] = scl[2 * i];
    for (let c = 0; c < 4; c++) { rotData[4 * i + c] = rot[4 * i + c]; colData[4 * i + c] = rgba[4 * i + c]; }
  }
  const texTri = makeTexture(gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, triData, N);
  const texMu = makeTexture(gl.RGBA32F, gl.RGBA, gl.FLOAT, muData, N);
  const texRot = makeTexture(gl.RGBA32F, gl.RGBA, gl.FLOAT, rotData, N);
  const texCol = makeTexture(gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, colData, N);
  const vertData = new Float32Array(TW * texHeight(V) * 4);
  const texVert = makeTexture(gl.RGBA32F, gl.RGBA, gl.FLOAT, vertData, V);
  // phase 2's surfel correction of the frame: local rotation dq (wxyz) and log scale factors
  const dqData = new Float32Array(padN * 4), lfData = new Float32Array(padN * 4);
  for (let i = 0; i < N; i++) dqData[4 * i] = 1;
  const texDq = makeTexture(gl.RGBA32F, gl.RGBA, gl.FLOAT, dqData, N);
  const texLf = makeTexture(gl.RGBA32F, gl.RGBA, gl.FLOAT, lfData, N);

  // ------------------------------------------------------------------ shaders
  // The surfel rasterizer's maths per pixel (sage_core/render/_project.py): the splat->pixel matrix M
  // (rows Tu, Tv, Tw) in OpenCV pixel coordinates, the ray-splat intersection (u, v) of each pixel,
  // rho = min(u^2 + v^2, 2 |c - x|^2) with the low-pass centre c the exact 3-sigma box centre, and the
  // pixels drawn those of the surfel's 16x16 tiles where alpha can reach 1/255.
  const VS = `#version 300 es
  precision highp float; precision highp int; precision highp usampler2D;
  uniform highp sampler2D uVert, uMu, uRot, uCol, uDq, uLf; uniform usampler2D uTri;
  uniform mat4 uView; uniform vec2 uSize; uniform vec4 uK; uniform float uNear;
  in uint aId;
  flat out vec3 vTu, vTv, vTw; flat out vec2 vCentre; out vec4 vColor;
  ivec2 px(uint i) { return ivec2(int(i % ${TW}u), int(i / ${TW}u)); }
  vec3 vert(uint i) { return texelFetch(uVert, px(i), 0).xyz; }
  mat3 quatMat(vec4 q) {
    q = q / length(q);
    float w = q.x, x = q.y, y = q.z, z = q.w;
    return mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
                2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
                2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
  }
  const vec2 corners[4] = vec2[4](vec2(0.0, 0.0), vec2(1.0, 0.0), vec2(0.0, 1.0), vec2(1.0, 1.0));
  void cull() { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); }
  void main() {
    uvec4 t = texelFetch(uTri, px(aId), 0);
    vec3 v0 = vert(t.x), v1 = vert(t.y), v2 = vert(t.z);
    vec3 e1 = v1 - v0, e2 = v2 - v0;
    vec3 a0 = e1 / sqrt(max(dot(e1, e1), 1e-20));
    vec3 n = cross(a0, e2);
    vec3 a1 = n / sqrt(max(dot(n, n), 1e-20));
    vec3 a2 = cross(a0, a1);
    float k = 0.5 * (length(e1) + abs(dot(a2, e2)));
    mat3 R = mat3(a0, a1, a2);
    vec4 m = texelFetch(uMu, px(aId), 0);
    mat3 Rs = R * quatMat(texelFetch(uRot, px(aId), 0)) * quatMat(texelFetch(uDq, px(aId), 0));
    vec3 centre = k * (R * m.xyz) + (v0 + v1 + v2) / 3.0;
    vec2 s = k * vec2(m.w, uintBitsToFloat(t.w)) * exp(texelFetch(uLf, px(aId), 0).xy);
    vColor = texelFetch(uCol, px(aId), 0);
    // OpenCV camera frame: the GL view matrix is diag(1, -1, -1) * w2c
    mat3 V = mat3(uView);
    vec3 flip = vec3(1.0, -1.0, -1.0);
    vec3 pc = flip * (uView * vec4(centre, 1.0)).xyz;
    vec3 ta = flip * (V * (Rs[0] * s.x)), tb = flip * (V * (Rs[1] * s.y)), nc = flip * (V * Rs[2]);
    mat3 K = mat3(uK.x, 0.0, 0.0, 0.0, uK.y, 0.0, uK.z, uK.w, 1.0);
    vec3 ca = K * ta, cb = K * tb, cc = K * pc;  // columns of M
    vec3 Tu = vec3(ca.x, cb.x, cc.x), Tv = vec3(ca.y, cb.y, cc.y), Tw = vec3(ca.z, cb.z, cc.z);
    float c2 = 9.0;
    float d = c2 * (Tw.x * Tw.x + Tw.y * Tw.y) - Tw.z * Tw.z;
    if (pc.z <= uNear || d >= 0.0 || dot(pc, nc) == 0.0) { cull(); return; }
    float cx = (c2 * (Tu.x * Tw.x + Tu.y * Tw.y) - Tu.z * Tw.z) / d;
    float cy = (c2 * (Tv.x * Tw.x + Tv.y * Tw.y) - Tv.z * Tw.z) / d;
    float uu = (c2 * (Tu.x * Tu.x + Tu.y * Tu.y) - Tu.z * Tu.z) / d;
    float vv = (c2 * (Tv.x * Tv.x + Tv.y * Tv.y) - Tv.z * Tv.z) / d;
    float r = ceil(max(max(sqrt(max(cx * cx - uu, 1e-4)), sqrt(max(cy * cy - vv, 1e-4))), 3.0 * 0.70710678));
    vec2 gridN = ceil(uSize / 16.0);
    vec2 c0 = vec2(cx, cy) - 0.5;  // pixel-index coordinates
    vec2 tile0 = clamp(floor((c0 - r) / 16.0), vec2(0.0), gridN);
    vec2 tile1 = clamp(floor((c0 + r + 15.0) / 16.0), vec2(0.0), gridN);
    if (tile1.x <= tile0.x || tile1.y <= tile0.y) { cull(); return; }
    // where alpha can reach 1/255: rho <= B, the projected disc of radius sqrt(B) and a square around c
    float B = max(0.0, 2.0 * log(max(255.0 * vColor.a, 1e-30)));
    vec2 lo = tile0 * 16.0, hi = tile1 * 16.0;
    vec2 blo = lo, bhi = hi;
    float dB = B * (Tw.x * Tw.x + Tw.y * Tw.y) - Tw.z * Tw.z;
    if (dB < 0.0) {
      float bx = (B * (Tu.x * Tw.x + Tu.y * Tw.y) - Tu.z * Tw.z) / dB;
      float by = (B * (Tv.x * Tw.x + Tv.y * Tw.y) - Tv.z * Tw.z) / dB;
      float hx = sqrt(max(bx * bx - (B * (Tu.x * Tu.x + Tu.y * Tu.y) - Tu.z * Tu.z) / dB, 0.0));
      float hy = sqrt(max(by * by - (B * (Tv.x * Tv.x + Tv.y * Tv.y) - Tv.z * Tv.z) / dB, 0.0));
      float q = sqrt(B / 2.0);
      blo = min(vec2(bx - hx, by - hy), vec2(cx, cy) - q) - 1.0;
      bhi = max(vec2(bx + hx, by + hy), vec2(cx, cy) + q) + 1.0;
    }
    lo = max(lo, blo); hi = min(hi, bhi);
    if (hi.x <= lo.x || hi.y <= lo.y) { cull(); return; }
    vec2 p = mix(lo, hi, corners[gl_VertexID]);
    gl_Position = vec4(2.0 * p.x / uSize.x - 1.0, 1.0 - 2.0 * p.y / uSize.y, 0.0, 1.0);
    vTu = Tu; vTv = Tv; vTw = Tw; vCentre = vec2(cx, cy);
  }`;
  const FS = `#version 300 es
  precision highp float;
  uniform vec2 uSize; uniform float uNear;
  flat in vec3 vTu, vTv, vTw; flat in vec2 vCentre; in vec4 vColor;
  out vec4 outColor;
  void main() {
    vec2 p = vec2(gl_FragCoord.x, uSize.y - gl_FragCoord.y);  // OpenCV pixel coordinates, centres at +0.5
    vec3 h = cross(p.x * vTw - vTu, p.y * vTw - vTv);
    if (h.z == 0.0) discard;
    vec2 uv = h.xy / h.z;
    if (dot(vTw, vec3(uv, 1.0)) < uNear) discard;  // the intersection lies before the near plane
    vec2 d = vCentre - p;
    float rho = min(dot(uv, uv), 2.0 * dot(d, d));
    float a = min(0.99, vColor.a * exp(-0.5 * rho));
    if (a < 1.0 / 255.0) discard;
    outColor = vec4(vColor.rgb * a, a);
  }`;
  function compile(type, src) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  const prog = gl.createProgram();
  try {
    gl.attachShader(prog, compile(gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  } catch (e) { fail("shader error: " + e.message); return; }
  gl.useProgram(prog);
  const U = {};
  for (const name of ["uVert", "uMu", "uRot", "uCol", "uTri", "uDq", "uLf", "uView", "uSize", "uK", "uNear"]) U[name] = gl.getUniformLocation(prog, name);
  const UNITS = [[texVert, "uVert"], [texMu, "uMu"], [texRot, "uRot"], [texCol, "uCol"], [texTri, "uTri"], [texDq, "uDq"], [texLf, "uLf"]];
  UNITS.forEach(([tex, name], unit) => {
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.uniform1i(U[name], unit);
  });
  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  const idBuf = gl.createBuffer();
  const aId = gl.getAttribLocation(prog, "aId");
  gl.bindBuffer(gl.ARRAY_BUFFER, idBuf);
  gl.bufferData(gl.ARRAY_BUFFER, N * 4, gl.DYNAMIC_DRAW);
  gl.enableVertexAttribArray(aId);
  gl.vertexAttribIPointer(aId, 1, gl.UNSIGNED_INT, 0, 0);
  gl.vertexAttribDivisor(aId, 1);

  // ------------------------------------------------------------------ frames and sorting
  const frameVerts = new Float32Array(V * 3);
  const centres = new Float32Array(N * 3);
  let loadedFrame = -1;
  function loadFrame(f) {
    const base = f * V * 3;
    for (let i = 0; i < V; i++) {
      for (let c = 0; c < 3; c++) {
        const v = qverts[base + 3 * i + c] * vs[c] + vo[c];
        frameVerts[3 * i + c] = v;
        vertData[4 * i + c] = v;
      }
    }
    gl.activeTexture(gl.TEXTURE0);  // texVert's unit
    gl.bindTexture(gl.TEXTURE_2D, texVert);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TW, texHeight(V), gl.RGBA, gl.FLOAT, vertData);
    if (frameCols) {  // this frame's colours (wrinkles, shading at the pose)
      const b = f * N * 3;
      for (let i = 0; i < N; i++) for (let c = 0; c < 3; c++) colData[4 * i + c] = frameCols[b + 3 * i + c];
      gl.activeTexture(gl.TEXTURE3);  // texCol's unit
      gl.bindTexture(gl.TEXTURE_2D, texCol);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TW, texHeight(N), gl.RGBA, gl.UNSIGNED_BYTE, colData);
    }
    if (frameDq) {  // this frame's surfel correction
      const b4 = f * N * 4, b2 = f * N * 2, lfs = doc.log_factor_scale;
      for (let i = 0; i < N; i++) {
        for (let c = 0; c < 4; c++) dqData[4 * i + c] = frameDq[b4 + 4 * i + c] / 127;
        lfData[4 * i] = frameLf[b2 + 2 * i] / lfs; lfData[4 * i + 1] = frameLf[b2 + 2 * i + 1] / lfs;
      }
      gl.activeTexture(gl.TEXTURE5);
      gl.bindTexture(gl.TEXTURE_2D, texDq);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TW, texHeight(N), gl.RGBA, gl.FLOAT, dqData);
      gl.activeTexture(gl.TEXTURE6);
      gl.bindTexture(gl.TEXTURE_2D, texLf);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TW, texHeight(N), gl.RGBA, gl.FLOAT, lfData);
    }
    // surfel centres on the CPU, only to sort them (the GPU poses everything it draws)
    for (let i = 0; i < N; i++) {
      const i0 = 3 * tri[3 * i], i1 = 3 * tri[3 * i + 1], i2 = 3 * tri[3 * i + 2];
      const e1x = frameVerts[i1] - frameVerts[i0], e1y = frameVerts[i1 + 1] - frameVerts[i0 + 1], e1z = frameVerts[i1 + 2] - frameVerts[i0 + 2];
      const e2x = frameVerts[i2] - frameVerts[i0], e2y = frameVerts[i2 + 1] - frameVerts[i0 + 1], e2z = frameVerts[i2 + 2] - frameVerts[i0 + 2];
      const l1 = Math.sqrt(Math.max(e1x * e1x + e1y * e1y + e1z * e1z, 1e-20));
      const a0x = e1x / l1, a0y = e1y / l1, a0z = e1z / l1;
      let nx = a0y * e2z - a0z * e2y, ny = a0z * e2x - a0x * e2z, nz = a0x * e2y - a0y * e2x;
      const ln = Math.sqrt(Math.max(nx * nx + ny * ny + nz * nz, 1e-20));
      nx /= ln; ny /= ln; nz /= ln;
      const a2x = a0y * nz - a0z * ny, a2y = a0z * nx - a0x * nz, a2z = a0x * ny - a0y * nx;
      const k = 0.5 * (l1 + Math.abs(a2x * e2x + a2y * e2y + a2z * e2z));
      const mx = k * mu[3 * i], my = k * mu[3 * i + 1], mz = k * mu[3 * i + 2];
      centres[3 * i] = a0x * mx + nx * my + a2x * mz + (frameVerts[i0] + frameVerts[i1] + frameVerts[i2]) / 3;
      centres[3 * i + 1] = a0y * mx + ny * my + a2y * mz + (frameVerts[i0 + 1] + frameVerts[i1 + 1] + frameVerts[i2 + 1]) / 3;
      centres[3 * i + 2] = a0z * mx + nz * my + a2z * mz + (frameVerts[i0 + 2] + frameVerts[i1 + 2] + frameVerts[i2 + 2]) / 3;
    }
    loadedFrame = f;
  }
  const order = new Uint32Array(N);
  const depthKey = new Uint32Array(N);
  const counts = new Uint32Array(65536);
  const depth = new Float32Array(N);
  function sortBackToFront(view) {  // view: column-major GL view matrix; camera looks along -z
    let lo = Infinity, hi = -Infinity;
    for (let i = 0; i < N; i++) {
      const z = view[2] * centres[3 * i] + view[6] * centres[3 * i + 1] + view[10] * centres[3 * i + 2] + view[14];
      depth[i] = z;  // more negative = farther
      if (z < lo) lo = z;
      if (z > hi) hi = z;
    }
    const span = hi > lo ? hi - lo : 1;
    counts.fill(0);
    for (let i = 0; i < N; i++) { depthKey[i] = Math.min(65535, Math.floor((depth[i] - lo) / span * 65535)); counts[depthKey[i]]++; }
    for (let b = 1; b < 65536; b++) counts[b] += counts[b - 1];
    for (let i = N - 1; i >= 0; i--) order[--counts[depthKey[i]]] = i;  // ascending z: far first
    gl.bindBuffer(gl.ARRAY_BUFFER, idBuf);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, order);
  }

  // ------------------------------------------------------------------ cameras
  const ref = doc.camera;
  const useRef = query.get("camera") === "ref";
  const W2C = ref.w2c;  // row-major 4x4, OpenCV
  const R0 = [[W2C[0], W2C[1], W2C[2]], [W2C[4], W2C[5], W2C[6]], [W2C[8], W2C[9], W2C[10]]];  // world -> camera rows
  const t0 = [W2C[3], W2C[7], W2C[11]];
  const camCentre = [0, 1, 2].map(j => -(R0[0][j] * t0[0] + R0[1][j] * t0[1] + R0[2][j] * t0[2]));
  const target = doc.head_center;
  const up = [-R0[1][0], -R0[1][1], -R0[1][2]];  // the reference camera's up (OpenCV y points down)
  let axes = [R0[0].slice(), R0[1].slice(), R0[2].slice()];  // camera x, y, z in world (rows)
  let dist = Math.hypot(camCentre[0] - target[0], camCentre[1] - target[1], camCentre[2] - target[2]);
  const home = { axes: axes.map(a => a.slice()), dist };
  function resetView() { axes = home.axes.map(a => a.slice()); dist = home.dist; dirty = true; }
  function rotateAbout(v, axis, ang) {  // Rodrigues
    const c = Math.cos(ang), s = Math.sin(ang);
    const d = axis[0] * v[0] + axis[1] * v[1] + axis[2] * v[2];
    const cr = [axis[1] * v[2] - axis[2] * v[1], axis[2] * v[0] - axis[0] * v[2], axis[0] * v[1] - axis[1] * v[0]];
    return [0, 1, 2].map(j => v[j] * c + cr[j] * s + axis[j] * d * (1 - c));
  }
  function cameraState() {  // -> {view (GL, column-major), fx, fy, cx, cy, width, height}
    let rows, centre, width, height, fx, fy, cx, cy;
    if (useRef) {
      rows = R0; centre = camCentre; width = ref.width; height = ref.height;
      fx = ref.fx; fy = ref.fy; cx = ref.cx; cy = ref.cy;
    } else {
      rows = axes;
      centre = [0, 1, 2].map(j => target[j] - dist * axes[2][j]);
      width = canvas.width; height = canvas.height;
      fy = ref.fy * height / ref.height; fx = fy; cx = width / 2; cy = height / 2;
    }
    const t = [0, 1, 2].map(r => -(rows[r][0] * centre[0] + rows[r][1] * centre[1] + rows[r][2] * centre[2]));
    const view = new Float32Array(16);  // diag(1, -1, -1, 1) · w2c, column-major
    const sign = [1, -1, -1];
    for (let r = 0; r < 3; r++) {
      for (let c = 0; c < 3; c++) view[c * 4 + r] = sign[r] * rows[r][c];
      view[12 + r] = sign[r] * t[r];
    }
    view[15] = 1;
    return { view, fx, fy, cx, cy, width, height };
  }


  // ------------------------------------------------------------------ drawing and controls
  let frame = Math.max(0, Math.min(T - 1, parseInt(query.get("frame") || "0", 10) || 0));
  let playing = !query.has("frame") && T > 1;
  let dirty = true, sortedFor = "";
  const requested = query.has("frame") ? frame : -1;
  if (query.get("ui") === "0") bar.classList.add("hidden");
  slider.max = String(T - 1);
  function resize() {
    if (useRef) {
      canvas.width = ref.width; canvas.height = ref.height;
      canvas.style.width = ref.width + "px"; canvas.style.height = ref.height + "px";
    } else {
      const dpr = window.devicePixelRatio || 1;
      canvas.width = Math.round(window.innerWidth * dpr); canvas.height = Math.round(window.innerHeight * dpr);
      canvas.style.width = window.innerWidth + "px"; canvas.style.height = window.innerHeight + "px";
    }
    dirty = true;
  }
  window.addEventListener("resize", resize);
  resize();
  function setPlaying(p) { playing = p && T > 1; playBtn.textContent = playing ? "pause" : "play"; }
  setPlaying(playing);
  playBtn.onclick = () => setPlaying(!playing);
  window.addEventListener("keydown", e => {
    if (e.code === "Space") { setPlaying(!playing); e.preventDefault(); }
    if (e.code === "KeyR") resetView();
  });
  resetBtn.onclick = resetView;
  let speed = parseFloat(query.get("speed") || "1");
  if (!(speed > 0)) speed = 1;
  if (![...speedSel.options].some(o => parseFloat(o.value) === speed)) speedSel.add(new Option(speed + "x", String(speed)));
  speedSel.value = String(speed);
  speedSel.onchange = () => { speed = parseFloat(speedSel.value); start = performance.now(); startFrame = frame; };
  window.sageSpeed = () => speed;
  slider.oninput = () => { frame = parseInt(slider.value, 10); setPlaying(false); dirty = true; };
  let drag = null;
  canvas.addEventListener("pointerdown", e => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", e => {
    if (!drag || useRef) return;
    const dx = e.clientX - drag[0], dy = e.clientY - drag[1];
    drag = [e.clientX, e.clientY];
    axes = axes.map(a => rotateAbout(a, up, -dx * 0.008));
    const x = axes[0];
    axes = axes.map(a => rotateAbout(a, x, dy * 0.008));
    dirty = true;
  });
  canvas.addEventListener("wheel", e => { if (!useRef) { dist *= Math.exp(e.deltaY * 0.001); dirty = true; } e.preventDefault(); }, { passive: false });

  const bg = doc.background;
  let start = performance.now(), startFrame = frame;
  let drawn = 0, fpsSince = performance.now();
  function draw() {
    if (frame !== loadedFrame) loadFrame(frame);
    const s = cameraState();
    const key = frame + ":" + Array.from(s.view).join(",");
    if (key !== sortedFor) { sortBackToFront(s.view); sortedFor = key; }
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.clearColor(bg[0], bg[1], bg[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.useProgram(prog);
    gl.uniformMatrix4fv(U.uView, false, s.view);
    gl.uniform2f(U.uSize, s.width, s.height);
    gl.uniform4f(U.uK, s.fx, s.fy, s.cx, s.cy);
    gl.uniform1f(U.uNear, doc.near || 0.2);
    gl.bindVertexArray(vao);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, N);
    slider.value = String(frame);
    label.textContent = `${frame + 1} / ${T}` + (doc.timesteps ? `  (timestep ${doc.timesteps[frame]})` : "");
    window.sageFrame = frame;
  }
  function tick(now) {
    if (playing) {
      const f = (startFrame + Math.floor((now - start) / 1000 * doc.fps * speed)) % T;
      if (f !== frame) { frame = f; dirty = true; }
    } else {
      start = now; startFrame = frame;
    }
    if (dirty) {
      draw();
      drawn++;
      dirty = false;
      if (!window.sageReady && (requested < 0 || frame === requested)) {
        requestAnimationFrame(() => { window.sageReady = true; });
      }
    }
    if (now - fpsSince >= 500) {  // frames drawn per second over the last half second
      window.sageFps = drawn * 1000 / (now - fpsSince);
      fpsLabel.textContent = drawn ? `${window.sageFps.toFixed(1)} fps` : "idle";
      drawn = 0; fpsSince = now;
    }
    requestAnimationFrame(tick);
  }
  msg.textContent = "";
  msg.classList.add("hidden");
  requestAnimationFrame(tick);
})();
