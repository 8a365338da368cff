// Drawing one map of the result from its float values: normals as RGB = (n + 1)/2, errors through
// the Turbo colour map (the server sends OpenCV's, so it matches error.png), depth and roughness as
// linear grey, reflectances (albedo, F0) display-encoded; the index gives each map's range.

import { BACKGROUND, toByte } from "./shading.js";

function level(v, lo, span) {
  const x = (v - lo) / span;
  return x > 0 ? (x < 1 ? x : 1) : 0;
}

// Draw map `name` ({shape: [H, W, C], range: [lo, hi], data}) on `canvas`; pixels outside `mask`
// (Uint8Array, H x W) and NaN values get the background; `colormap` is 256 RGB triples.
export function drawMap(canvas, map, name, mask, colormap) {
  const [h, w, c] = map.shape;
  canvas.width = w;
  canvas.height = h;
  const ctx = canvas.getContext("2d");
  const image = ctx.createImageData(w, h);
  const out = image.data;
  const d = map.data;
  const [lo, hi] = map.range;
  const span = hi - lo || 1;
  for (let i = 0, o = 0; i < w * h; i++, o += 4) {
    out[o + 3] = 255;
    const first = d[c * i];
    if (!mask[i] || Number.isNaN(first)) {
      out[o] = BACKGROUND[0];
      out[o + 1] = BACKGROUND[1];
      out[o + 2] = BACKGROUND[2];
      continue;
    }
    if (name === "normal") {
      for (let k = 0; k < 3; k++) out[o + k] = Math.round(((d[3 * i + k] + 1) / 2) * 255);
    } else if (name === "error") {
      const rgb = colormap[Math.floor(level(first, lo, span) * 255 + 0.5)];
      out[o] = rgb[0];
      out[o + 1] = rgb[1];
      out[o + 2] = rgb[2];
    } else if (name === "depth" || name === "roughness" || c === 1) {
      const g = Math.round(level(first, lo, span) * 255);
      out[o] = out[o + 1] = out[o + 2] = g;
    } else {
      for (let k = 0; k < 3; k++) out[o + k] = toByte(level(d[3 * i + k], lo, span));
    }
  }
  ctx.putImageData(image, 0, 0);
}

// Draw RGB bytes (H x W x 3, row-major) on `canvas`.
export function drawRGB(canvas, bytes, w, h) {
  canvas.width = w;
  canvas.height = h;
  const ctx = canvas.getContext("2d");
  const image = ctx.createImageData(w, h);
  const out = image.data;
  for (let i = 0, o = 0; i < w * h; i++, o += 4) {
    out[o] = bytes[3 * i];
    out[o + 1] = bytes[3 * i + 1];
    out[o + 2] = bytes[3 * i + 2];
    out[o + 3] = 255;
  }
  ctx.putImageData(image, 0, 0);
}

// CSS size for a canvas of w x h: small maps enlarged by a whole factor to about `target` pixels,
// large ones shrunk to it.
export function showAt(canvas, w, h, target) {
  const side = Math.max(w, h);
  const factor = side < target ? Math.max(1, Math.floor(target / side)) : target / side;
  canvas.style.width = `${Math.round(w * factor)}px`;
  canvas.style.height = `${Math.round(h * factor)}px`;
}
