// Loading the viewer's data files. They are scripts (data/*.js), not fetched binaries, so that the page works from
// file:// as well as from a server: each assigns {sections, data} into window.IAV: a base64, zlib-compressed buffer
// of byte-shuffled arrays and its table of typed arrays (avatar/viewer/codec.py's pack_sections).

import { unzlibSync } from "fflate";

const TYPES = {
  uint8: Uint8Array,
  int8: Int8Array,
  uint16: Uint16Array,
  int16: Int16Array,
  uint32: Uint32Array,
  float32: Float32Array,
  float16: Uint16Array, // decoded to Float32Array by halfToFloat
};

// IEEE half-precision bits -> Float32Array.
function halfToFloat(bits) {
  const out = new Float32Array(bits.length);
  for (let i = 0; i < bits.length; i++) {
    const h = bits[i];
    const sign = h & 0x8000 ? -1 : 1;
    const exponent = (h >> 10) & 0x1f;
    const fraction = h & 0x3ff;
    if (exponent === 0) out[i] = sign * 2 ** -14 * (fraction / 1024);
    else if (exponent === 31) out[i] = fraction ? NaN : sign * Infinity;
    else out[i] = sign * 2 ** (exponent - 15) * (1 + fraction / 1024);
  }
  return out;
}

function bytesOf(base64) {
  const text = atob(base64);
  const bytes = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
  return bytes;
}

// name -> typed array view of the entry's buffer.
export function unpack(entry) {
  const raw = unzlibSync(bytesOf(entry.data));
  const out = {};
  for (const [name, s] of Object.entries(entry.sections)) {
    const count = s.shape.reduce((a, b) => a * b, 1);
    const Type = TYPES[s.dtype];
    if (!Type) throw new Error(`${name}: unknown dtype ${s.dtype}`);
    const size = Type.BYTES_PER_ELEMENT;
    const bytes = new Uint8Array(count * size);
    for (let b = 0; b < size; b++) {
      const plane = raw.subarray(s.offset + b * count, s.offset + (b + 1) * count);
      for (let i = 0; i < count; i++) bytes[i * size + b] = plane[i];
    }
    out[name] = s.dtype === "float16" ? halfToFloat(new Type(bytes.buffer)) : new Type(bytes.buffer);
  }
  return out;
}

// Run the script at `src` (relative to the page) once; resolves when it has run.
export function loadScript(src) {
  return new Promise((resolve, reject) => {
    const script = document.createElement("script");
    script.src = src;
    script.onload = () => resolve();
    script.onerror = () => reject(new Error(`cannot load ${src}: rerun the pipeline's viewer stage`));
    document.head.appendChild(script);
  });
}
