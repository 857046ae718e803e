// The job page: state, explanation and actions; settings and times; the image drawn from
// tile events; tile grid, shards, phases, statistics, A/B comparison and the live log.
"use strict";

import { Compare, exactBaseline } from "./compare.js";
import { LogView } from "./logs.js";
import { drawPhaseChart, showSettings, showShards, showStats, showTimes, TileGrid } from "./panels.js";
import { $, api, authHeaders, LIVE, TERMINAL } from "./util.js";
import { base64Bytes, decodeHalf, fetchPixels, Viewer } from "./viewer.js";

const TICK_MS = 1000; // how often a live job's duration is redrawn
const MESH_DECISION = /mesh \d+ '.*': (proxy|replicate|none|fallback) \(/;

const viewer = new Viewer($("#job-canvas"), {
  onPixel: (x, y, [r, g, b]) => { $("#pixel-readout").textContent = `(${x}, ${y}) linear ${r.toFixed(4)} ${g.toFixed(4)} ${b.toFixed(4)}`; },
});
const grid = new TileGrid($("#tile-grid"));
const logs = new LogView($("#log-view"), $("#log-status"));
const compare = new Compare($("#compare-panel"));

let current = null;   // the job shown (JobPublic)
let source = null;    // its event stream
let pending = null;   // tile events that arrive while the first /pixels fetch is in flight
let tick = null;
let prep = null;      // what the log says a preparing job is doing

export function closeJob() {
  if (source) source.close();
  source = null;
  clearInterval(tick);
  logs.close();
  compare.close();
  current = null;
}

export function openJob(id) {
  closeJob();
  current = { id };
  prep = { decided: 0, meshes: null, last: "" };
  pending = null;
  viewer.rgb = null;
  $("#image-empty").hidden = false;
  $("#job-canvas").hidden = true;
  $("#downloads").hidden = true;
  $("#job-error").textContent = "";
  $("#action-error").textContent = "";
  logs.open(id, onLogLine);
  source = new EventSource(`/v1/jobs/${id}/events?pixels=f16`);
  let first = true;
  source.addEventListener("state", (ev) => {
    const job = JSON.parse(ev.data);
    if (first) startJob(job);
    first = false;
    showJob(job);
    if (job.state === "succeeded") loadPixels(job); // the final image, whatever tiles were missed
    if (TERMINAL.has(job.state)) closeSource();
  });
  source.addEventListener("tile", (ev) => onTile(JSON.parse(ev.data)));
  source.addEventListener("end", closeSource);
  source.onerror = () => { if (source) $("#job-error").textContent = "event stream interrupted; retrying"; };
  tick = setInterval(() => { if (current?.state && LIVE.has(current.state)) showTimes(current); }, TICK_MS);
}

function closeSource() {
  if (source) source.close();
  source = null;
}

function startJob(job) {
  viewer.reset(job.settings.width, job.settings.height);
  grid.reset(job);
  if (job.passes_done > 0 && job.state !== "succeeded") loadPixels(job);
  if (job.settings.mode !== "exact") {
    api(`/v1/scenes/${encodeURIComponent(job.scene)}`).then((s) => { prep.meshes = s.summary?.base_meshes ?? null; explain(current); }).catch(() => {});
  }
}

async function loadPixels(job) {
  pending = pending || [];
  try {
    const img = await fetchPixels(job.id, authHeaders());
    if (current?.id !== job.id) return;
    if (img) {
      viewer.setImage(img.rgb);
      showImage(true);
    }
  } catch (e) {
    $("#job-error").textContent = `image: ${e.message}`;
  } finally {
    const late = pending || [];
    pending = null;
    late.forEach(onTile); // tiles newer than the fetched image
  }
}

function onTile(t) {
  if (pending) { pending.push(t); return; }
  if (t.pixels) {
    const [x0, y0, x1, y1] = t.rect;
    const rgb = decodeHalf(base64Bytes(t.pixels));
    if (rgb.length === (x1 - x0) * (y1 - y0) * 3) {
      viewer.setTile(t.rect, rgb);
      showImage(true);
    }
  }
  grid.tile(t.rect, t.sample1);
  showProgress(t.progress);
}

function showImage(has) {
  $("#image-empty").hidden = has;
  $("#job-canvas").hidden = !has;
  $("#downloads").hidden = !has;
}

function showProgress(fraction) {
  const pct = Math.round(fraction * 100);
  const bar = $("#job-progress");
  bar.style.width = `${pct}%`;
  bar.setAttribute("aria-valuenow", pct);
  $("#job-progress-text").textContent = `${pct}%`;
}

function onLogLine(line) {
  if (MESH_DECISION.test(line)) prep.decided += 1;
  prep.last = line.replace(/^\S+ \S+ \S+ /, ""); // drop date, time and level
  if (current?.state === "preparing") explain(current);
}

// What the job is waiting for, in words (the issue: 40 s of "preparing" said nothing).
function explain(job) {
  const s = job.settings;
  const box = $("#job-explain");
  let text = "";
  if (job.state === "queued") {
    text = "Queued: waiting for a free job slot" + (s.shards ? " (sharded jobs also wait for the shard slot)" : "") + ".";
  } else if (job.state === "preparing") {
    text = s.shards
      ? `Preparing: loading scene ${job.scene}, partitioning its instances over ${s.shards} shards` +
        (s.mode === "proxy" ? `, fetching or training a proxy for each base mesh that crosses shards (${s.proxy.steps} optimiser steps of training each, unless cached)` : "") +
        (s.mode === "oracle" ? ", deciding which meshes to replicate" : "") +
        `, and starting ${s.shards} shard actors. A warm pool of the same scene and placement skips this.`
      : `Preparing: loading scene ${job.scene} for the single-process reference renderer.`;
    if (s.mode !== "exact" && prep.meshes) text += ` Base meshes decided: ${prep.decided} of ${prep.meshes}.`;
    if (prep.last) text += ` Latest: ${prep.last}`;
  } else if (job.state === "running") {
    text = `Rendering: ${job.passes_done} of ${job.passes_total} passes stored (passes finish out of order).`;
  }
  box.textContent = text;
  box.hidden = !text;
}

// A frames job: pick a frame and see its stored image (the canvas above shows the frame
// being rendered, tile by tile). Frames render in order, each `per` passes, and a frame's
// images are written before the next frame's first pass: so a frame is ready once the job
// succeeded or passes_done is past it. Frames not ready are listed but not fetched.
function frameReady(job, frame) {
  if (!job?.frames) return false;
  if (job.state === "succeeded") return true;
  const { first, last } = job.frames;
  const per = job.passes_total / (last - first + 1);
  return job.passes_done > (frame - first + 1) * per;
}

function showFrames(job) {
  const panel = $("#frame-panel");
  panel.hidden = !job.frames;
  if (!job.frames) return;
  const select = $("#frame-select");
  const { first, last } = job.frames;
  const fresh = select.dataset.job !== job.id;
  if (fresh) {
    select.dataset.job = job.id;
    select.replaceChildren();
    for (let f = first; f <= last; f++) select.append(new Option(String(f), String(f)));
    select.value = String(first);
  }
  for (const opt of select.options) {
    const ready = frameReady(job, Number(opt.value));
    opt.textContent = ready ? opt.value : `${opt.value} (not rendered yet)`;
    opt.dataset.ready = ready ? "1" : "";
  }
  if (fresh || job.state === "succeeded" || $("#frame-image").hidden) {
    loadFrame(job.id, Number(select.value));
  }
}

async function loadFrame(id, frame) {
  $("#frame-png-link").href = `/v1/jobs/${id}/frames/${frame}.png`;
  $("#frame-exr-link").href = `/v1/jobs/${id}/frames/${frame}.exr`;
  const img = $("#frame-image");
  const status = $("#frame-status");
  if (!frameReady(current, frame)) {
    img.hidden = true;
    status.textContent = `frame ${frame} is not rendered yet`;
    return;
  }
  const r = await fetch(`/v1/jobs/${id}/frames/${frame}.png`, { headers: authHeaders(), cache: "no-store" });
  if (current?.id !== id) return;
  if (!r.ok) {
    img.hidden = true;
    status.textContent = r.status === 404 ? `frame ${frame} is not rendered yet` : `frame ${frame}: ${r.status}`;
    return;
  }
  if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
  img.src = URL.createObjectURL(await r.blob());
  img.hidden = false;
  status.textContent = "";
}

$("#frame-select").addEventListener("change", (ev) => { if (current) loadFrame(current.id, Number(ev.target.value)); });

function showJob(job) {
  const prev = current?.state;
  current = job;
  $("#job-id").textContent = job.id;
  const state = $("#job-state");
  state.textContent = job.state;
  state.className = `state ${job.state}`;
  showProgress(job.progress);
  $("#job-error").textContent = job.error || "";
  $("#cancel-button").hidden = !LIVE.has(job.state);
  $("#requeue-button").hidden = !TERMINAL.has(job.state);
  $("#delete-button").hidden = !TERMINAL.has(job.state);
  $("#png-link").href = `/v1/jobs/${job.id}/image.png`;
  $("#exr-link").href = `/v1/jobs/${job.id}/image.exr`;
  explain(job);
  showFrames(job);
  showSettings(job);
  showTimes(job);
  showShards(job);
  drawPhaseChart(job);
  if (job.state === "succeeded") grid.complete();
  const baseline = job.state === "succeeded" ? exactBaseline(job).catch(() => null) : Promise.resolve(null);
  baseline.then((b) => { if (current === job) showStats(job, b); });
  showStats(job, null);
  if (prev !== job.state && TERMINAL.has(job.state)) compare.open(job);
  else if (!TERMINAL.has(job.state)) compare.open(job);
}

async function action(fn) {
  $("#action-error").textContent = "";
  try {
    await fn();
  } catch (e) {
    $("#action-error").textContent = e.message;
  }
}

$("#cancel-button").addEventListener("click", () => action(async () => {
  showJob(await api(`/v1/jobs/${current.id}/cancel`, { method: "POST" }));
}));

// Requeue: the same scene and settings as a new job.
$("#requeue-button").addEventListener("click", () => action(async () => {
  const body = { scene: current.scene, ...current.settings, frames: current.frames };
  const job = await api("/v1/jobs", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
  location.hash = `#/jobs/${job.id}`;
}));

$("#delete-button").addEventListener("click", () => action(async () => {
  if (!confirm(`Delete job ${current.id} with its image and log?`)) return;
  await api(`/v1/jobs/${current.id}`, { method: "DELETE" });
  location.hash = "#/";
}));

$("#exposure").addEventListener("input", (ev) => {
  const v = Number(ev.target.value);
  $("#exposure-value").textContent = `${v > 0 ? "+" : ""}${v.toFixed(1)} EV`;
  viewer.setExposure(v);
  compare.setExposure(v);
});

$("#zoom").addEventListener("change", (ev) => viewer.setZoom(ev.target.value));

$("#job-canvas").addEventListener("wheel", (ev) => {
  if (!ev.ctrlKey && !ev.altKey) return; // plain wheel scrolls the page
  ev.preventDefault();
  const steps = ["fit", "1", "2", "4", "8"];
  const i = steps.indexOf(String(viewer.zoom));
  const next = steps[Math.min(steps.length - 1, Math.max(0, i + (ev.deltaY < 0 ? 1 : -1)))];
  $("#zoom").value = next;
  viewer.setZoom(next);
}, { passive: false });
