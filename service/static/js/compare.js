// A/B view: a proxy (or oracle) job against the exact job of the same scene, seed and image
// settings; a slider, a flicker, and a map of the per-pixel error.
"use strict";

import { $, api, authHeaders, el, shortId } from "./util.js";
import { fetchPixels, Viewer } from "./viewer.js";

const SAME = ["width", "height", "spp", "bounces", "shadow_rays", "seed", "russian_roulette"];
const FLICKER_MS = 600;

// The newest succeeded exact job that renders the same image (any shard count: exact is
// exact), preferring the same shard count.
export async function exactBaseline(job) {
  if (job.settings.mode === "exact") return null;
  const jobs = await api("/v1/jobs?state=succeeded&limit=500");
  const same = jobs.data.filter((j) => j.scene === job.scene && j.settings.mode === "exact" &&
    SAME.every((k) => j.settings[k] === job.settings[k]));
  return same.find((j) => j.settings.shards === job.settings.shards) || same[0] || null;
}

// Per-pixel mean absolute error over the channels -> (errors, summary).
export function errorStats(a, b) {
  const n = a.length / 3, err = new Float32Array(n);
  let se = 0, ae = 0, max = 0, mean = 0;
  for (let p = 0; p < n; p++) {
    let e = 0;
    for (let c = 0; c < 3; c++) {
      const d = b[3 * p + c] - a[3 * p + c];
      se += d * d;
      e += Math.abs(d);
      mean += a[3 * p + c];
    }
    err[p] = e / 3;
    ae += e;
    if (err[p] > max) max = err[p];
  }
  const rmse = Math.sqrt(se / (3 * n));
  return { err, rmse, mae: ae / (3 * n), max, relRmse: rmse / Math.max(mean / (3 * n), 1e-12) };
}

// error / scale in [0, 1] -> black, red, yellow, white.
function heat(t) {
  t = Math.min(1, Math.max(0, t)) * 3;
  return [Math.min(1, t), Math.min(1, Math.max(0, t - 1)), Math.min(1, Math.max(0, t - 2))].map((v) => Math.round(255 * v));
}

export class Compare {
  constructor(panel) {
    this.panel = panel;
    this.a = new Viewer($("#compare-a", panel));
    this.b = new Viewer($("#compare-b", panel));
    this.timer = null;
    $("#compare-slider", panel).addEventListener("input", () => this._clip());
    for (const r of panel.querySelectorAll("input[name=compare-mode]")) r.addEventListener("change", () => this._mode());
    $("#error-scale", panel).addEventListener("change", () => this._drawError());
    $("#compare-exact-button", panel).addEventListener("click", () => this._renderExact());
  }

  close() {
    clearInterval(this.timer);
    this.timer = null;
    this.job = null;
  }

  async open(job) {
    this.close();
    this.job = job;
    const eligible = job.settings.mode !== "exact" && job.state === "succeeded";
    this.panel.hidden = job.settings.mode === "exact";
    if (!eligible) {
      this._status(job.settings.mode === "exact" ? "" : "the comparison appears once this job succeeds");
      $("#compare-body", this.panel).hidden = true;
      return;
    }
    const base = await exactBaseline(job);
    if (this.job !== job) return;
    $("#compare-exact-button", this.panel).hidden = !!base;
    if (!base) {
      this._status("no succeeded exact job renders this image yet (same scene, seed, size, spp, bounces, shadow rays)");
      $("#compare-body", this.panel).hidden = true;
      return;
    }
    const [a, b] = await Promise.all([fetchPixels(base.id, authHeaders()), fetchPixels(job.id, authHeaders())]);
    if (this.job !== job || !a || !b) return;
    for (const [v, img] of [[this.a, a], [this.b, b]]) {
      v.reset(img.width, img.height);
      v.setExposure(this.exposure || 0);
      v.setImage(img.rgb);
    }
    this.stats = errorStats(a.rgb, b.rgb);
    const s = this.stats;
    this._status("");
    $("#compare-what", this.panel).replaceChildren("A: exact job ", el("a", { href: `#/jobs/${base.id}` }, shortId(base.id)),
      ` (${base.settings.shards} shards) · B: this ${job.settings.mode} job`);
    $("#compare-stats", this.panel).replaceChildren(...[
      ["RMSE", s.rmse.toExponential(3)], ["relative RMSE", `${(100 * s.relRmse).toFixed(2)}%`],
      ["mean abs error", s.mae.toExponential(3)], ["max pixel error", s.max.toExponential(3)],
    ].map(([k, v]) => el("tr", { "data-key": k }, el("td", {}, k), el("td", {}, v))));
    $("#compare-body", this.panel).hidden = false;
    this._drawError();
    this._mode();
  }

  setExposure(ev) {
    this.exposure = ev;
    this.a.setExposure(ev);
    this.b.setExposure(ev);
  }

  _status(text) { $("#compare-status", this.panel).textContent = text; }

  _mode() {
    const mode = $("input[name=compare-mode]:checked", this.panel).value;
    clearInterval(this.timer);
    this.timer = null;
    const stage = $("#compare-stage", this.panel);
    stage.hidden = mode === "error";
    $("#error-map", this.panel).hidden = mode !== "error";
    $("#slider-row", this.panel).hidden = mode !== "slider";
    $("#error-row", this.panel).hidden = mode !== "error";
    const label = $("#flicker-label", this.panel);
    label.hidden = mode !== "flicker";
    if (mode === "slider") this._clip();
    if (mode === "flicker") {
      let showB = true;
      const flip = () => {
        this.b.canvas.style.clipPath = showB ? "none" : "inset(0 0 0 100%)";
        label.textContent = showB ? `B: ${this.job.settings.mode}` : "A: exact";
        showB = !showB;
      };
      flip();
      this.timer = setInterval(flip, FLICKER_MS);
    }
  }

  _clip() {
    const pct = Number($("#compare-slider", this.panel).value);
    // B (this job) covers the left pct%: A shows through on the right.
    this.b.canvas.style.clipPath = `inset(0 ${100 - pct}% 0 0)`;
    $("#compare-divider", this.panel).style.left = `${pct}%`;
  }

  _drawError() {
    if (!this.stats) return;
    const scale = Number($("#error-scale", this.panel).value);
    const { width, height } = this.a;
    const canvas = $("#error-map", this.panel);
    canvas.width = width;
    canvas.height = height;
    const ctx = canvas.getContext("2d");
    const img = ctx.createImageData(width, height);
    this.stats.err.forEach((e, p) => {
      const [r, g, b] = heat(e / scale);
      img.data.set([r, g, b, 255], 4 * p);
    });
    ctx.putImageData(img, 0, 0);
  }

  async _renderExact() {
    const s = this.job.settings;
    const body = { scene: this.job.scene, ...s, mode: "exact" };
    try {
      const exact = await api("/v1/jobs", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
      this._status(`exact job ${shortId(exact.id)} queued; the comparison appears when it succeeds`);
      $("#compare-exact-button", this.panel).hidden = true;
      const job = this.job;
      const poll = setInterval(async () => {
        if (this.job !== job) return clearInterval(poll);
        const j = await api(`/v1/jobs/${exact.id}`).catch(() => null);
        if (j && ["succeeded", "failed", "canceled"].includes(j.state)) {
          clearInterval(poll);
          if (j.state === "succeeded") this.open(job); else this._status(`exact job ${shortId(exact.id)} ${j.state}`);
        }
      }, 1000);
    } catch (e) {
      this._status(e.message);
    }
  }
}
