// The depth map as a point cloud, turned by dragging: each pixel with a depth is a point
// (u - cx, cy - v, depth) in pixel units (depth.npy is the height towards the camera in pixels),
// rotated about the vertical axis (yaw) and then the horizontal one (pitch), projected
// orthographically and splatted into a z-buffer, coloured by the relit image.

const TURN_PER_PIXEL = 0.01; // radians per pixel dragged

export class Orbit {
  // canvas: the drawing surface; depth: {shape: [H, W, 1], data}; mask: Uint8Array (H x W);
  // yaw, pitch: start angles in radians.
  constructor(canvas, depth, mask, yaw, pitch) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.yaw = yaw;
    this.pitch = pitch;
    const [h, w] = depth.shape;
    const d = depth.data;
    const pixels = [];
    let mean = 0;
    for (let i = 0; i < w * h; i++) {
      if (mask[i] && Number.isFinite(d[i])) {
        pixels.push(i);
        mean += d[i];
      }
    }
    mean = pixels.length ? mean / pixels.length : 0;
    this.count = pixels.length;
    this.pixel = Int32Array.from(pixels);
    this.x = new Float32Array(this.count);
    this.y = new Float32Array(this.count);
    this.z = new Float32Array(this.count);
    let radius = 1;
    for (let j = 0; j < this.count; j++) {
      const i = this.pixel[j];
      this.x[j] = (i % w) - (w - 1) / 2;
      this.y[j] = (h - 1) / 2 - Math.floor(i / w);
      this.z[j] = d[i] - mean;
      radius = Math.max(radius, Math.hypot(this.x[j], this.y[j], this.z[j]));
    }
    this.scale = (0.48 * Math.min(canvas.width, canvas.height)) / radius;
    // a point stands for one pixel of the map: splat squares a little larger than the spacing of
    // neighbours on screen, so a surface seen head-on stays closed
    this.splat = Math.max(1, Math.min(24, Math.ceil(this.scale) + 1));
    this.zbuffer = new Float32Array(canvas.width * canvas.height);
    this.colours = null;
    this._drag(canvas);
  }

  // Redraw; `colours` (RGBA bytes of the relit image, H x W) replaces the previous ones if given.
  render(colours) {
    if (colours) this.colours = colours;
    const { width, height } = this.canvas;
    const image = this.ctx.createImageData(width, height);
    const out = image.data;
    const zb = this.zbuffer;
    zb.fill(-Infinity);
    for (let o = 0; o < out.length; o += 4) {
      out[o] = 17;
      out[o + 1] = 17;
      out[o + 2] = 20;
      out[o + 3] = 255;
    }
    const cy = Math.cos(this.yaw);
    const sy = Math.sin(this.yaw);
    const cp = Math.cos(this.pitch);
    const sp = Math.sin(this.pitch);
    const half = Math.floor(this.splat / 2);
    const rgba = this.colours;
    for (let j = 0; j < this.count; j++) {
      const x1 = this.x[j] * cy + this.z[j] * sy;
      const z1 = -this.x[j] * sy + this.z[j] * cy;
      const y2 = this.y[j] * cp - z1 * sp;
      const z2 = this.y[j] * sp + z1 * cp;
      const px = Math.round(width / 2 + x1 * this.scale) - half;
      const py = Math.round(height / 2 - y2 * this.scale) - half;
      const src = 4 * this.pixel[j];
      for (let dy = 0; dy < this.splat; dy++) {
        const row = py + dy;
        if (row < 0 || row >= height) continue;
        for (let dx = 0; dx < this.splat; dx++) {
          const col = px + dx;
          if (col < 0 || col >= width) continue;
          const at = row * width + col;
          if (z2 <= zb[at]) continue;
          zb[at] = z2;
          const o = 4 * at;
          if (rgba) {
            out[o] = rgba[src];
            out[o + 1] = rgba[src + 1];
            out[o + 2] = rgba[src + 2];
          } else {
            out[o] = out[o + 1] = out[o + 2] = 200;
          }
        }
      }
    }
    this.ctx.putImageData(image, 0, 0);
  }

  _drag(canvas) {
    let last = null;
    let queued = false;
    canvas.addEventListener("pointerdown", (e) => {
      last = [e.clientX, e.clientY];
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointerup", () => {
      last = null;
    });
    canvas.addEventListener("pointermove", (e) => {
      if (!last) return;
      this.yaw += (e.clientX - last[0]) * TURN_PER_PIXEL;
      this.pitch = Math.max(-Math.PI / 2, Math.min(Math.PI / 2, this.pitch + (e.clientY - last[1]) * TURN_PER_PIXEL));
      last = [e.clientX, e.clientY];
      if (!queued) {
        queued = true;
        requestAnimationFrame(() => {
          queued = false;
          this.render();
        });
      }
    });
  }
}
