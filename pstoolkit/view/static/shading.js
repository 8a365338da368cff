// Per-pixel shading with the toolkit's BRDF, as pstoolkit/optics/brdf.py writes it: Lambertian
// albedo plus, with F0 and roughness maps, a GGX lobe (no 1/pi on the diffuse part), seen from
// v = (0, 0, 1). pstoolkit/view/display.py computes the same picture in Python; the tests compare.

const MIN_ROUGHNESS = 0.02;
const HALF_EPS = 1e-12;
const GAMMA = 1 / 2.2;
export const BACKGROUND = [24, 24, 27];

// "x,y,z" as a unit vector, or null when it is not three finite numbers of non-zero length.
export function parseLight(text) {
  if (!text) return null;
  const v = text.split(",").map(Number);
  if (v.length !== 3 || !v.every(Number.isFinite)) return null;
  const norm = Math.hypot(v[0], v[1], v[2]);
  return norm > 0 ? v.map((x) => x / norm) : null;
}

// Linear value (1 = white) to a display byte: round(255 * clip(v, 0, 1)^(1/2.2)); NaN is 0.
export function toByte(v) {
  return v > 0 ? Math.round(255 * Math.pow(v < 1 ? v : 1, GAMMA)) : 0;
}

export class Shader {
  // index: /data/index.json; maps: name -> {shape: [H, W, C], data: Float32Array}.
  constructor(index, maps) {
    this.width = index.width;
    this.height = index.height;
    this.count = this.width * this.height;
    this.normal = maps.normal.data;
    this.albedo = maps.albedo ? maps.albedo.data : null;
    this.albedoChannels = maps.albedo ? maps.albedo.shape[2] : 0;
    this.ggx = index.brdf === "ggx" && !!maps.f0 && !!maps.roughness;
    this.f0 = this.ggx ? maps.f0.data : null;
    this.f0Channels = this.ggx ? maps.f0.shape[2] : 0;
    this.roughness = this.ggx ? maps.roughness.data : null;
    // the server zeroes the normal outside the mask
    this.mask = new Uint8Array(this.count);
    const n = this.normal;
    for (let i = 0; i < this.count; i++) {
      this.mask[i] = n[3 * i] !== 0 || n[3 * i + 1] !== 0 || n[3 * i + 2] !== 0 ? 1 : 0;
    }
  }

  // Fill `image` (ImageData of width x height) with the surface under the unit `light` (x right,
  // y up, z to the camera), each channel's radiance times scale[c] (exposure x light intensity).
  render(image, light, scale) {
    const out = image.data;
    const n = this.normal;
    const a = this.albedo;
    const ac = this.albedoChannels;
    const f0 = this.f0;
    const fc = this.f0Channels;
    const rough = this.roughness;
    const [lx, ly, lz] = light;
    // v = (0, 0, 1), so the half vector is the same for every pixel
    const sx = lx;
    const sy = ly;
    const sz = lz + 1;
    const ss = sx * sx + sy * sy + sz * sz;
    const inv = 1 / Math.sqrt(ss + HALF_EPS);
    const hx = sx * inv;
    const hy = sy * inv;
    const hz = sz * inv;
    const lift = HALF_EPS / (ss + HALF_EPS);
    for (let i = 0, o = 0; i < this.count; i++, o += 4) {
      out[o + 3] = 255;
      if (!this.mask[i]) {
        out[o] = BACKGROUND[0];
        out[o + 1] = BACKGROUND[1];
        out[o + 2] = BACKGROUND[2];
        continue;
      }
      const nx = n[3 * i];
      const ny = n[3 * i + 1];
      const nz = n[3 * i + 2];
      const nl = Math.max(nx * lx + ny * ly + nz * lz, 0);
      let ar = 1;
      let ag = 1;
      let ab = 1;
      if (ac === 3) {
        ar = a[3 * i];
        ag = a[3 * i + 1];
        ab = a[3 * i + 2];
      } else if (ac === 1) {
        ar = ag = ab = a[i];
      }
      let sr = 0;
      let sg = 0;
      let sb = 0;
      if (this.ggx) {
        const r = Math.max(rough[i], MIN_ROUGHNESS);
        const alpha2 = r * r * r * r;
        const k = ((r + 1) * (r + 1)) / 8;
        const nv = Math.max(nz, 0);
        const nh = nx * hx + ny * hy + nz * hz;
        // 1 - (n.h)^2 as |n x h|^2, as brdf.py does: no cancellation near the peak
        const cx = ny * hz - nz * hy;
        const cy = nz * hx - nx * hz;
        const cz = nx * hy - ny * hx;
        const q = cx * cx + cy * cy + cz * cz + lift + nh * nh * alpha2;
        const d = alpha2 / (Math.PI * q * q);
        const spec = d / (4 * (nl * (1 - k) + k) * (nv * (1 - k) + k));
        if (fc === 3) {
          sr = spec * f0[3 * i];
          sg = spec * f0[3 * i + 1];
          sb = spec * f0[3 * i + 2];
        } else {
          sr = sg = sb = spec * f0[i];
        }
      }
      out[o] = toByte((ar + sr) * nl * scale[0]);
      out[o + 1] = toByte((ag + sg) * nl * scale[1]);
      out[o + 2] = toByte((ab + sb) * nl * scale[2]);
    }
  }
}
