// Posing the avatar's Gaussians for one frame: the browser's half of avatar/viewer/codec.py, step by step the same
// as its decode_frame (triangle_frames of avatar/geometry/frames.py, then the frame's geometry and appearance
// overrides).

const EPS = 1e-12;

// v / |v| into out[o..o+3], or the fallback (already unit) where |v| is tiny; returns out.
function normalise(x, y, z, fallback, out) {
  const n2 = x * x + y * y + z * z;
  if (n2 > EPS) {
    const n = Math.sqrt(n2);
    out[0] = x / n;
    out[1] = y / n;
    out[2] = z / n;
  } else {
    out[0] = fallback[0];
    out[1] = fallback[1];
    out[2] = fallback[2];
  }
  return out;
}

function cross(a, b) {
  return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
}

// A unit vector perpendicular to the unit vector a (frames.py's _any_perpendicular).
function anyPerpendicular(a) {
  const abs = a.map(Math.abs);
  const smallest = abs[0] <= abs[1] && abs[0] <= abs[2] ? 0 : abs[1] <= abs[2] ? 1 : 2;
  const helper = [0, 0, 0];
  helper[smallest] = 1;
  const c = cross(a, helper);
  return normalise(c[0], c[1], c[2], [0, 0, 1], [0, 0, 0]);
}

// Rotation matrix (row-major m[3*i+j]) -> unit quaternion [w, x, y, z].
function matrixToQuaternion(m, out, o) {
  const trace = m[0] + m[4] + m[8];
  let w;
  let x;
  let y;
  let z;
  if (trace > 0) {
    const s = Math.sqrt(trace + 1) * 2;
    w = s / 4;
    x = (m[7] - m[5]) / s;
    y = (m[2] - m[6]) / s;
    z = (m[3] - m[1]) / s;
  } else if (m[0] > m[4] && m[0] > m[8]) {
    const s = Math.sqrt(1 + m[0] - m[4] - m[8]) * 2;
    w = (m[7] - m[5]) / s;
    x = s / 4;
    y = (m[1] + m[3]) / s;
    z = (m[2] + m[6]) / s;
  } else if (m[4] > m[8]) {
    const s = Math.sqrt(1 + m[4] - m[0] - m[8]) * 2;
    w = (m[2] - m[6]) / s;
    x = (m[1] + m[3]) / s;
    y = s / 4;
    z = (m[5] + m[7]) / s;
  } else {
    const s = Math.sqrt(1 + m[8] - m[0] - m[4]) * 2;
    w = (m[3] - m[1]) / s;
    x = (m[2] + m[6]) / s;
    y = (m[5] + m[7]) / s;
    z = s / 4;
  }
  out[o] = w;
  out[o + 1] = x;
  out[o + 2] = y;
  out[o + 3] = z;
}

// The frames of the triangles `used` on the dequantised vertices: origin (3), rotation (9, row-major, columns a0
// a1 a2), scale (1), quaternion (4) per used triangle, in `frames` (Float64Array(17 * used.length)).
export function triangleFrames(vertices, ranges, levels, faces, used, frames) {
  const lo = ranges.vertex_lo;
  const step = ranges.vertex_hi.map((hi, i) => (hi - lo[i]) / levels);
  const v = [
    [0, 0, 0],
    [0, 0, 0],
    [0, 0, 0],
  ];
  const a0 = [0, 0, 0];
  const a1 = [0, 0, 0];
  const a2 = [0, 0, 0];
  const m = new Float64Array(9);
  for (let u = 0; u < used.length; u++) {
    const f = used[u];
    for (let c = 0; c < 3; c++) {
      const vi = faces[3 * f + c];
      for (let d = 0; d < 3; d++) v[c][d] = lo[d] + vertices[3 * vi + d] * step[d];
    }
    const e1 = [v[1][0] - v[0][0], v[1][1] - v[0][1], v[1][2] - v[0][2]];
    const e2 = [v[2][0] - v[0][0], v[2][1] - v[0][1], v[2][2] - v[0][2]];
    const fallbackEdge = normalise(e2[0], e2[1], e2[2], [1, 0, 0], [0, 0, 0]);
    normalise(e1[0], e1[1], e1[2], fallbackEdge, a0);
    const perpendicular = anyPerpendicular(a0);
    const n = cross(a0, e2);
    normalise(n[0], n[1], n[2], perpendicular, a1);
    const t = cross(a0, a1);
    normalise(t[0], t[1], t[2], perpendicular, a2);
    const base = Math.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2] + EPS);
    const height = Math.abs(a2[0] * e2[0] + a2[1] * e2[1] + a2[2] * e2[2]);
    const o = 17 * u;
    for (let d = 0; d < 3; d++) {
      frames[o + d] = (v[0][d] + v[1][d] + v[2][d]) / 3;
      m[3 * d] = a0[d];
      m[3 * d + 1] = a1[d];
      m[3 * d + 2] = a2[d];
    }
    frames.set(m, o + 3);
    frames[o + 12] = Math.max((base + height) / 2, 1e-6);
    matrixToQuaternion(m, frames, o + 13);
  }
}

// Hamilton product a * b of [w, x, y, z] quaternions read from arrays at offsets.
function multiply(a, ao, b, bo, out, o) {
  const aw = a[ao];
  const ax = a[ao + 1];
  const ay = a[ao + 2];
  const az = a[ao + 3];
  const bw = b[bo];
  const bx = b[bo + 1];
  const by = b[bo + 2];
  const bz = b[bo + 3];
  out[o] = aw * bw - ax * bx - ay * by - az * bz;
  out[o + 1] = aw * bx + ax * bw + ay * bz - az * by;
  out[o + 2] = aw * by - ax * bz + ay * bw + az * bx;
  out[o + 3] = aw * bz + ax * by - ay * bx + az * bw;
}

// The Gaussians of frame t: the static ones on the frame's triangles, then the frame's overrides. Writes
// out.centers (N*3), out.scales (N*3), out.quats (N*4, w x y z), out.rgba (N*4, 0..1).
export function poseFrame(avatar, motion, t, out) {
  const { statics, used, usedIndex, frames } = avatar;
  const N = statics.triangle.length;
  const V = motion.sections.vertices.length / (3 * motion.frames);
  const vertices = motion.sections.vertices.subarray(3 * V * t, 3 * V * (t + 1));
  triangleFrames(vertices, motion.ranges, avatar.vertexLevels, statics.faces, used, frames);
  const lm = statics.local_means;
  const ls = statics.local_log_scales;
  const lq = statics.local_quats;
  const q = new Float64Array(4);
  for (let i = 0; i < N; i++) {
    const o = 17 * usedIndex[i];
    const k = frames[o + 12];
    for (let d = 0; d < 3; d++) {
      const r = o + 3 + 3 * d;
      out.centers[3 * i + d] = k * (frames[r] * lm[3 * i] + frames[r + 1] * lm[3 * i + 1] + frames[r + 2] * lm[3 * i + 2]) + frames[o + d];
      out.scales[3 * i + d] = Math.exp(ls[3 * i + d]) * k;
    }
    multiply(frames, o + 13, lq, 4 * i, q, 0);
    const n = Math.hypot(q[0], q[1], q[2], q[3]);
    for (let d = 0; d < 4; d++) {
      out.quats[4 * i + d] = q[d] / n;
      out.rgba[4 * i + d] = statics.rgba[4 * i + d] / 255;
    }
  }
  const s = motion.sections;
  const STEPS = avatar.steps; // the steps of the overrides' int16 deltas (avatar/viewer/codec.py's STEPS)
  const bytes = Math.ceil(N / 8);
  const turn = new Float64Array(4);
  forEachSet(s.geometry_mask, bytes * t, N, s.geometry_start[t], (i, j) => {
    for (let d = 0; d < 3; d++) {
      out.centers[3 * i + d] += s.d_mean[3 * j + d] * STEPS.mean;
      out.scales[3 * i + d] *= Math.exp(s.d_log_scale[3 * j + d] * STEPS.log_scale);
    }
    rotationQuaternion(s.d_rotation[3 * j] * STEPS.rotation, s.d_rotation[3 * j + 1] * STEPS.rotation, s.d_rotation[3 * j + 2] * STEPS.rotation, turn);
    multiply(turn, 0, out.quats, 4 * i, q, 0);
    out.quats.set(q, 4 * i);
  });
  forEachSet(s.appearance_mask, bytes * t, N, s.appearance_start[t], (i, j) => {
    for (let d = 0; d < 4; d++) {
      const level = Math.round(out.rgba[4 * i + d] * 255) + s.d_rgba[4 * j + d];
      out.rgba[4 * i + d] = Math.min(Math.max(level / 255, 0), 1);
    }
  });
}

// A rotation vector (axis times angle) -> unit quaternion [w, x, y, z] in out.
function rotationQuaternion(x, y, z, out) {
  const angle = Math.hypot(x, y, z);
  const scale = angle > 1e-12 ? Math.sin(angle / 2) / angle : 0.5;
  out[0] = Math.cos(angle / 2);
  out[1] = x * scale;
  out[2] = y * scale;
  out[3] = z * scale;
}

// Calls visit(i, j) for each set bit i < N of the mask starting at mask[offset] (little-endian bits), j counting
// up from `first` (the bit's record in the frame's packed overrides).
function forEachSet(mask, offset, N, first, visit) {
  let j = first;
  for (let byte = 0; byte * 8 < N; byte++) {
    const bits = mask[offset + byte];
    if (!bits) continue;
    for (let bit = 0; bit < 8; bit++) {
      if (bits & (1 << bit)) visit(8 * byte + bit, j++);
    }
  }
}

// The triangles the Gaussians ride on (sorted, unique) and, per Gaussian, its triangle's slot in that list.
export function usedTriangles(triangle) {
  const used = Array.from(new Set(triangle)).sort((a, b) => a - b);
  const slot = new Map(used.map((f, u) => [f, u]));
  return { used: Uint32Array.from(used), usedIndex: Uint32Array.from(triangle, (f) => slot.get(f)) };
}
