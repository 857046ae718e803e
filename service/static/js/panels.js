// The job page's read-only panels: settings, times, statistics, shards, phases, tile grid.
"use strict";

import { $, el, fmtBytes, fmtInt, fmtSeconds, durationS, svg, sum, TERMINAL } from "./util.js";

const PROXY_MODES = new Set(["proxy", "oracle"]);

function kvRows(table, rows) {
  $("tbody", table).replaceChildren(...rows.map(([k, v]) => el("tr", { "data-key": k }, el("td", {}, k), el("td", {}, v))));
}

export function showSettings(job) {
  const s = job.settings;
  const rows = [
    ["scene", job.scene],
    ["resolution", `${s.width} × ${s.height}`],
    ["samples per pixel", `${s.spp} (${s.spp_per_pass} per pass)`],
    ["bounces", s.bounces],
    ["shadow rays per hit", s.shadow_rays],
    ["russian roulette", s.russian_roulette ? "on" : "off"],
    ["seed", s.seed],
    ["mode", s.mode],
    ["shards", s.shards ? s.shards : "0 (single-process reference)"],
    ...(s.shards > 1 && s.byte_slack !== undefined
      ? [["shard bytes cap", `${s.byte_slack}× the bytes-only placement's largest shard`]] : []),
    ["tile size", `${s.tile_size} px`],
    ["passes", fmtInt(job.passes_total)],
  ];
  if (PROXY_MODES.has(s.mode) && s.proxy) {  // proxy knobs mean nothing in exact mode
    const p = s.proxy;
    rows.push(["proxy threshold", p.threshold ?? "each proxy's calibrated one"],
      ["accuracy target", p.accuracy === null || p.accuracy === undefined ? "hand-set bands" : (p.accuracy === "exact" ? "exact" : `${p.accuracy} dB${p.check ? ", checked" : ""}`)],
      ["proxy band", p.accuracy === null || p.accuracy === undefined ? `${p.band} (shadow rays: ${p.shadow_band})` : "per proxy, from its error curve"],
      ["proxy width", p.width ?? `narrowest meeting ${p.accuracy_target}`],
      ["proxy budget", `${p.steps} optimiser steps per proxy`]);
  }
  kvRows($("#settings-table"), rows);
}

const fmtTime = (iso) => (iso ? new Date(iso).toLocaleString() : "–");

export function showTimes(job) {
  const st = job.stats || {};
  const queued = job.started_at ? (Date.parse(job.started_at) - Date.parse(job.created_at)) / 1000 : null;
  const rows = [
    ["created", fmtTime(job.created_at)],
    ["started", fmtTime(job.started_at)],
    ["finished", fmtTime(job.finished_at)],
    ["waited in queue", queued === null ? "–" : fmtSeconds(queued)],
    [TERMINAL.has(job.state) ? "duration" : "running for", fmtSeconds(durationS(job))],
  ];
  if (st.wall_s !== undefined) rows.push(["render wall time", fmtSeconds(st.wall_s)]);
  if (st.accuracy) {  // target, prediction and check of a proxy-mode job
    const a = st.accuracy, c = a.check, db = (x) => (x === null || x === undefined ? "∞" : `${x} dB`);
    rows.push(["predicted PSNR", db(a.predicted_db)]);
    if (c && typeof c === "object") rows.push(["checked PSNR", `${db(c.psnr_db)} (95 %: ${db(c.interval_db[0])} to ${db(c.interval_db[1])})`]);
    if (a.warning) rows.push(["⚠ accuracy", a.warning]);
  }
  if (st.prepare_s !== undefined) rows.push(["preparation", `${fmtSeconds(st.prepare_s)}${st.warm_pool ? " (warm pool: none)" : ""}`]);
  kvRows($("#times-table"), rows);
}

export function showStats(job, baseline) {
  const s = job.stats;
  const rows = [];
  if (s) {
    if (s.renderer) rows.push(["renderer", s.renderer]);
    if (s.scene) rows.push(["scene", `${fmtInt(s.scene.instances)} instances, ${fmtInt(s.scene.instanced_triangles)} triangles`]);
    for (const [kind, n] of Object.entries(s.rays || {})) rows.push([`${kind} rays`, fmtInt(n)]);
    rows.push(["rays total", fmtInt(sum(s.rays))]);
    for (const [kind, n] of Object.entries(s.transfers || {})) {
      if (n) rows.push([`${kind} transfers`, `${fmtInt(n)} (${fmtBytes(s.bytes?.[kind] || 0)})`]);
    }
    rows.push(["transfers total", `${fmtInt(s.total_transfers || 0)} (${fmtBytes(s.total_bytes || 0)})`]);
    if (s.checkpoint_bytes !== undefined) rows.push(["checkpoints written", fmtBytes(s.checkpoint_bytes)]);
    if (s.coordinator_wait_s !== undefined) rows.push(["coordinator waiting", fmtSeconds(s.coordinator_wait_s)]);
    if (s.coordinator_cpu_s != null) rows.push(["coordinator CPU", fmtSeconds(s.coordinator_cpu_s)]);
    const shardCpu = (s.shard_stats || []).filter((x) => x.cpu_s != null);
    if (shardCpu.length) rows.push(["shard CPU total", fmtSeconds(shardCpu.reduce((a, x) => a + x.cpu_s, 0))]);
    if (s.hops_histogram?.length) rows.push(["hops histogram", s.hops_histogram.join(" / ")]);
    for (const [k, v] of Object.entries(s.counters || {})) rows.push([k.replaceAll("_", " "), fmtInt(v)]);
    for (const t of s.proxy_training || []) {  // one Ray task per proxy, live while preparing
      const took = t.seconds == null ? "" : ` in ${fmtSeconds(t.seconds)}`;
      const acc = t.accuracy == null ? "" : `, ${(100 * t.accuracy).toFixed(2)}% held-out`;
      rows.push([`training ${t.name ?? "mesh " + t.mesh}`, `${t.state}${took}${acc}${t.error ? ": " + t.error : ""}`]);
    }
    for (const d of s.proxy_plan?.decisions || []) {
      const what = d.decision === "proxy" ? `proxy, width ${d.width}, ${(100 * d.accuracy).toFixed(2)}% held-out, ${fmtBytes(d.proxy_bytes)}` : d.decision;
      rows.push([`mesh ${d.name}`, `${what}: ${d.reason}`]);
    }
    if (baseline?.stats) {
      const saved = baseline.stats.total_bytes - (s.total_bytes || 0);
      const pct = baseline.stats.total_bytes ? ` (${(100 * saved / baseline.stats.total_bytes).toFixed(1)}%)` : "";
      rows.push(["bytes saved vs exact", `${fmtBytes(saved)}${pct} against job ${baseline.id.slice(0, 8)}`]);
    }
  }
  if (job.pixel_samples) rows.push(["samples per pixel", `${job.pixel_samples.min}–${job.pixel_samples.max}`]);
  kvRows($("#stats-table"), rows);
}

export function showShards(job) {
  const shards = job.stats?.shard_stats;
  const box = $("#shard-panel");
  if (!job.settings.shards) {
    box.replaceChildren(el("p", { class: "muted" }, "single-process reference render: no shards"));
    return;
  }
  if (!shards) {
    box.replaceChildren(el("p", { class: "muted" }, `${job.settings.shards} shards; their figures arrive when the job finishes`));
    return;
  }
  const cpu = shards.some((s) => s.cpu_s != null);  // CPU seconds, when the coordinator reports them
  const head = el("tr", {}, ...["shard", "node", "pid", "geometry", "busy", ...(cpu ? ["CPU"] : []), "calls", "bytes in", "bytes out"].map((h) => el("th", {}, h)));
  const rows = shards.map((s) => el("tr", { "data-shard": s.shard },
    el("td", {}, s.shard), el("td", { title: s.node || "" }, (s.node || "–").slice(0, 12)), el("td", {}, s.pid),
    el("td", {}, fmtBytes(s.geometry_bytes)),
    el("td", { class: "busy" }, el("div", { class: "bar small" },
      el("div", { class: "fill", style: `width:${Math.min(100, 100 * s.busy_fraction).toFixed(1)}%` }),
      el("span", {}, `${(100 * s.busy_fraction).toFixed(1)}%`))),
    ...(cpu ? [el("td", { class: "cpu" }, s.cpu_s == null ? "–" : fmtSeconds(s.cpu_s))] : []),
    el("td", {}, fmtInt(s.calls)), el("td", {}, fmtBytes(s.bytes_in)), el("td", {}, fmtBytes(s.bytes_out))));
  const coordinator = job.stats.coordinator_cpu_s;
  box.replaceChildren(el("table", { id: "shard-table" }, el("thead", {}, head), el("tbody", {}, ...rows)),
    el("p", { class: "muted" }, "busy: the shard's seconds of work over the job's wall time" +
      (cpu ? "; CPU: the shard process's CPU seconds in this job" : "") +
      (coordinator == null ? "" : `; coordinator CPU: ${fmtSeconds(coordinator)}`)));
}

// phase_s sums each stage's seconds over all shards; divided by the shard count it is the
// mean seconds one shard spent in it, comparable with the job's wall time. transfer_wait is
// different: each pass's parcel latency, summed over passes in flight at once, so it
// overlaps itself and is shown apart, never as a share of the wall time.
const OVERLAPPING = { transfer_wait: "parcel latency summed over the passes in flight, which overlap: not a share of the wall time" };

export function drawPhaseChart(job) {
  const phases = job.stats?.phase_s || {};
  const k = Math.max(1, job.settings.shards);
  const wall = job.stats?.wall_s;
  const box = $("#phase-chart");
  const entries = Object.entries(phases).filter(([n]) => !(n in OVERLAPPING))
    .map(([n, s]) => [n, s / k]).sort((a, b) => b[1] - a[1]);
  if (!entries.length) { box.textContent = "no timings yet"; return; }
  const rows = [...entries];
  const shards = job.stats?.shard_stats;
  if (shards?.length) rows.push(["shard busy", shards.reduce((a, x) => a + x.busy_s, 0) / shards.length]);
  if (wall) rows.push(["wall time", wall]);
  const barH = 18, gap = 6, labelW = 110, width = 460;
  const max = Math.max(...rows.map((r) => r[1]), 1e-9);
  const chart = svg("svg", { width: "100%", viewBox: `0 0 ${width} ${rows.length * (barH + gap)}`, id: "phase-svg" });
  rows.forEach(([name, secs], i) => {
    const y = i * (barH + gap);
    const w = Math.max(1, (width - labelW - 120) * secs / max);
    const total = name === "wall time" || name === "shard busy";
    const pct = wall && name !== "wall time" ? ` (${(100 * secs / wall).toFixed(0)}% of wall)` : "";
    chart.append(svg("text", { x: 0, y: y + 13 }, name),
      svg("rect", { x: labelW, y, width: w, height: barH, rx: 2, fill: total ? "#1d232b" : "#2f6fde", "data-phase": name }),
      svg("text", { x: labelW + w + 4, y: y + 13 }, `${secs.toFixed(3)} s${pct}`));
  });
  const who = job.settings.shards
    ? `Mean seconds per shard: each stage's time summed over the ${k} shards, divided by ${k}; "shard busy" is the mean of the shards' busy seconds`
    : "Seconds in each stage of the single-process render";
  const notes = Object.entries(OVERLAPPING).filter(([n]) => n in phases)
    .map(([n, why]) => el("li", { "data-phase": n }, `${n}: ${phases[n].toFixed(3)} s, ${why}`));
  const caption = el("p", { class: "muted", id: "phase-caption" }, `${who}${wall ? ", against the job's wall time" : ""}.`);
  box.replaceChildren(chart, caption, ...(notes.length ? [el("ul", { class: "muted" }, ...notes)] : []));
}

// One cell per tile, shaded by the samples it holds; tile events raise a cell's count.
export class TileGrid {
  constructor(box) { this.box = box; }

  reset(job) {
    const s = job.settings;
    this.spp = s.spp;
    this.tileSize = s.tile_size;
    this.nx = Math.ceil(s.width / s.tile_size);
    this.ny = Math.ceil(s.height / s.tile_size);
    // Passes go chunk by chunk over all tiles (finishing out of order within a window):
    // the finished chunks are a floor for every tile.
    const chunks = Math.floor(job.passes_done / (this.nx * this.ny));
    const floor = job.state === "succeeded" ? s.spp : Math.min(s.spp, chunks * s.spp_per_pass);
    this.samples = new Array(this.nx * this.ny).fill(floor);
    const cell = Math.max(4, Math.min(24, Math.floor(300 / Math.max(this.nx, this.ny))));
    this.svg = svg("svg", { id: "tile-svg", width: this.nx * cell, height: this.ny * cell, viewBox: `0 0 ${this.nx} ${this.ny}` });
    this.cells = this.samples.map((_, i) => {
      const r = svg("rect", { x: i % this.nx, y: Math.floor(i / this.nx), width: 0.92, height: 0.92, "data-tile": i });
      this.svg.append(r);
      return r;
    });
    this.box.replaceChildren(this.svg, el("p", { class: "muted" }, `${this.nx} × ${this.ny} tiles of ${this.tileSize} px; shade = samples done out of ${this.spp}`));
    this.cells.forEach((_, i) => this._paint(i));
  }

  tile([x0, y0], sample1) {
    const i = Math.floor(y0 / this.tileSize) * this.nx + Math.floor(x0 / this.tileSize);
    if (sample1 > this.samples[i]) {
      this.samples[i] = sample1;
      this._paint(i);
    }
  }

  complete() {
    this.samples.fill(this.spp);
    this.cells.forEach((_, i) => this._paint(i));
  }

  _paint(i) {
    const f = this.samples[i] / this.spp;
    const c = this.cells[i];
    c.setAttribute("fill", f >= 1 ? "#1f9d55" : f > 0 ? `rgba(47,111,222,${0.25 + 0.75 * f})` : "#e9edf2");
    c.setAttribute("data-samples", this.samples[i]);
  }
}
