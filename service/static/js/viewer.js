// A linear-light image on a canvas: filled from /pixels and from SSE tile events
// (float16), shown with an exposure (EV) and the sRGB curve, zoomable.
"use strict";

// float16 -> float32 for every 16-bit pattern (256 KiB, built once).
const HALF = (() => {
  const t = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, m = h & 0x3ff;
    t[h] = e === 0 ? s * m * 2 ** -24 : e === 31 ? (m ? NaN : s * Infinity) : s * (1 + m / 1024) * 2 ** (e - 15);
  }
  return t;
})();

// Linear [0, 1] -> sRGB byte, 4096 steps: the same curve as workers/film.py tonemap_srgb.
const SRGB = (() => {
  const t = new Uint8ClampedArray(4097);
  for (let i = 0; i <= 4096; i++) {
    const x = i / 4096;
    t[i] = Math.round(255 * (x <= 0.0031308 ? 12.92 * x : 1.055 * x ** (1 / 2.4) - 0.055));
  }
  return t;
})();

export function decodeHalf(bytes) {
  const u16 = new Uint16Array(bytes.buffer, bytes.byteOffset, bytes.byteLength / 2);
  const out = new Float32Array(u16.length);
  for (let i = 0; i < u16.length; i++) out[i] = HALF[u16[i]];
  return out;
}

export function base64Bytes(b64) {
  const s = atob(b64);
  const out = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
  return out;
}

// The job's current image: {width, height, rgb: Float32Array (h * w * 3), partial}; null
// before the first pass (404).
export async function fetchPixels(jobId, headers) {
  const r = await fetch(`/v1/jobs/${jobId}/pixels`, { headers, cache: "no-store" });
  if (r.status === 404) return null;
  if (!r.ok) throw new Error(`${r.status}: ${await r.text()}`);
  const width = Number(r.headers.get("X-Nprt-Width")), height = Number(r.headers.get("X-Nprt-Height"));
  const rgb = decodeHalf(new Uint8Array(await r.arrayBuffer()));
  return { width, height, rgb, partial: r.headers.get("X-Nprt-Partial") === "true" };
}

// rgb (w*h*3 linear) -> RGBA bytes of rect [x0, x1) x [y0, y1), times `scale`.
export function toRgba(rgb, width, x0, y0, x1, y1, scale, out) {
  let o = 0;
  for (let y = y0; y < y1; y++) {
    for (let x = x0; x < x1; x++) {
      const i = (y * width + x) * 3;
      for (let c = 0; c < 3; c++) {
        const v = rgb[i + c] * scale;
        out[o++] = SRGB[v >= 1 ? 4096 : v > 0 ? Math.round(v * 4096) : 0];
      }
      out[o++] = 255;
    }
  }
  return out;
}

export class Viewer {
  constructor(canvas, { onPixel } = {}) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.exposure = 0;
    this.zoom = "fit";
    this.rgb = null;
    this.onPixel = onPixel;
    canvas.addEventListener("mousemove", (ev) => this._hover(ev));
  }

  get hasImage() { return this.rgb !== null; }

  reset(width, height) {
    this.width = width;
    this.height = height;
    this.rgb = null;
    this.canvas.width = width;
    this.canvas.height = height;
    this.ctx.clearRect(0, 0, width, height);
    this.applyZoom();
  }

  // Replace the whole image (w*h*3 linear floats).
  setImage(rgb) {
    this.rgb = rgb;
    this.redraw();
  }

  // One tile's linear pixels, (y1-y0) x (x1-x0) x 3.
  setTile([x0, y0, x1, y1], tile) {
    if (!this.rgb) this.rgb = new Float32Array(this.width * this.height * 3);
    const tw = x1 - x0;
    for (let y = y0; y < y1; y++) {
      this.rgb.set(tile.subarray((y - y0) * tw * 3, (y - y0 + 1) * tw * 3), (y * this.width + x0) * 3);
    }
    this._draw(x0, y0, x1, y1);
  }

  setExposure(ev) {
    this.exposure = ev;
    this.redraw();
  }

  redraw() {
    if (this.rgb) this._draw(0, 0, this.width, this.height);
  }

  _draw(x0, y0, x1, y1) {
    const img = this.ctx.createImageData(x1 - x0, y1 - y0);
    toRgba(this.rgb, this.width, x0, y0, x1, y1, 2 ** this.exposure, img.data);
    this.ctx.putImageData(img, x0, y0);
  }

  // "fit" (the panel's width) or a factor: 1 = one screen pixel per image pixel.
  setZoom(zoom) {
    this.zoom = zoom;
    this.applyZoom();
  }

  applyZoom() {
    const c = this.canvas;
    if (this.zoom === "fit") {
      c.style.width = "100%";
      c.style.maxWidth = "";
    } else {
      c.style.width = `${this.width * Number(this.zoom)}px`;
      c.style.maxWidth = "none";
    }
  }

  _hover(ev) {
    if (!this.rgb || !this.onPixel) return;
    const r = this.canvas.getBoundingClientRect();
    const x = Math.floor((ev.clientX - r.left) / r.width * this.width);
    const y = Math.floor((ev.clientY - r.top) / r.height * this.height);
    if (x < 0 || y < 0 || x >= this.width || y >= this.height) return;
    const i = (y * this.width + x) * 3;
    this.onPixel(x, y, [this.rgb[i], this.rgb[i + 1], this.rgb[i + 2]]);
  }
}
