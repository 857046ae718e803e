// nprt dashboard: job list (polled), demo submission, and a live job page (SSE).
"use strict";

const TERMINAL = new Set(["succeeded", "failed", "canceled"]);
const LIST_POLL_MS = 1000;
const $ = (sel) => document.querySelector(sel);

const tokenInput = $("#token");
tokenInput.value = localStorage.getItem("nprt-token") || "";
tokenInput.addEventListener("change", () => localStorage.setItem("nprt-token", tokenInput.value));

function authHeaders() {
  const t = tokenInput.value.trim();
  return t ? { Authorization: `Bearer ${t}` } : {};
}

async function api(path, options = {}) {
  const r = await fetch(path, { ...options, headers: { ...authHeaders(), ...(options.headers || {}) } });
  const body = r.headers.get("content-type")?.includes("json") ? await r.json() : await r.text();
  if (!r.ok) {
    const d = body && body.detail;
    const msg = Array.isArray(d) ? d.map((e) => `${e.loc.slice(1).join(".")}: ${e.msg}`).join("; ") : d || body;
    throw new Error(`${r.status}: ${msg}`);
  }
  return body;
}

const fmtBytes = (n) => n >= 1 << 20 ? `${(n / (1 << 20)).toFixed(2)} MiB` : n >= 1024 ? `${(n / 1024).toFixed(1)} KiB` : `${n} B`;
const fmtInt = (n) => Number(n).toLocaleString("en-US");
const sum = (obj) => Object.values(obj || {}).reduce((a, b) => a + b, 0);
const shortId = (id) => id.slice(0, 8);

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}

function progressBar(fraction) {
  const pct = Math.round(fraction * 100);
  const fill = el("div", { class: "fill", style: `width:${pct}%`, role: "progressbar", "aria-valuenow": pct });
  return el("div", { class: "bar" }, fill, el("span", {}, `${pct}%`));
}

// ------------------------------------------------------------------ list view

let listTimer = null;

async function loadScenes() {
  const scenes = await api("/v1/scenes");
  const select = $("#scene-select");
  select.replaceChildren(...scenes.data.map((s) =>
    el("option", { value: s.id, "data-kind": s.kind }, s.kind === "demo" ? s.id : `${s.summary?.name || s.filename} (${shortId(s.id)})`)));
}

async function refreshList() {
  try {
    const jobs = await api("/v1/jobs?limit=50");
    $("#job-count").textContent = `(${jobs.count})`;
    $("#job-table tbody").replaceChildren(...jobs.data.map((j) => el("tr", { "data-job": j.id },
      el("td", {}, el("a", { href: `#/jobs/${j.id}` }, shortId(j.id))),
      el("td", {}, j.scene.length > 40 ? shortId(j.scene) : j.scene),
      el("td", {}, `${j.settings.width}×${j.settings.height}, ${j.settings.spp} spp`),
      el("td", {}, `${j.settings.mode}${j.settings.shards ? ` ×${j.settings.shards}` : ""}`),
      el("td", {}, el("span", { class: `state ${j.state}` }, j.state)),
      el("td", {}, progressBar(j.progress)),
      el("td", {}, new Date(j.created_at).toLocaleTimeString()))));
  } catch (e) {
    $("#job-count").textContent = `(${e.message})`;
  }
}

$("#submit-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const f = new FormData(ev.target);
  const kind = $("#scene-select").selectedOptions[0]?.dataset.kind;
  const size = f.get("size");
  const body = { scene: kind === "demo" && size ? `${f.get("scene")}:${size}` : f.get("scene"), mode: f.get("mode") };
  for (const k of ["width", "height", "spp", "bounces", "shadow_rays", "shards", "tile_size", "spp_per_pass", "seed"]) {
    body[k] = Number(f.get(k));
  }
  if (body.mode === "proxy") body.proxy = { band: Number(f.get("band")), shadow_band: Number(f.get("shadow_band")) };
  $("#submit-error").textContent = "";
  try {
    const job = await api("/v1/jobs", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    location.hash = `#/jobs/${job.id}`;
  } catch (e) {
    $("#submit-error").textContent = e.message;
  }
});

// ------------------------------------------------------------------ job view

let source = null;
let current = null; // the job shown
let imageBusy = false, imageDirty = false, imageVersion = 0;

function refreshImage() {
  // One load in flight at a time; tiles that land meanwhile coalesce into one reload.
  if (imageBusy) { imageDirty = true; return; }
  imageBusy = true;
  const img = $("#job-image");
  const probe = new Image();
  probe.onload = () => { img.src = probe.src; done(); };
  probe.onerror = done;
  probe.src = `/v1/jobs/${current.id}/image.png?v=${++imageVersion}`;
  function done() {
    imageBusy = false;
    if (imageDirty) { imageDirty = false; refreshImage(); }
  }
}

function showProgress(fraction) {
  const pct = Math.round(fraction * 100);
  const bar = $("#job-progress");
  bar.style.width = `${pct}%`;
  bar.setAttribute("aria-valuenow", pct);
  $("#job-progress-text").textContent = `${pct}%`;
}

async function exactBaseline(job) {
  // "Bytes saved against exact": the newest succeeded exact job with the same scene and settings.
  if (job.settings.mode === "exact") return null;
  const jobs = await api("/v1/jobs?state=succeeded&limit=500");
  const keys = ["width", "height", "spp", "bounces", "shadow_rays", "seed", "shards", "tile_size", "spp_per_pass"];
  return jobs.data.find((j) => j.scene === job.scene && j.settings.mode === "exact" &&
    keys.every((k) => j.settings[k] === job.settings[k])) || null;
}

async function showStats(job) {
  const s = job.stats;
  const rows = [];
  if (s) {
    if (s.wall_s !== undefined) rows.push(["wall time", `${s.wall_s.toFixed(2)} s`]);
    if (s.renderer) rows.push(["renderer", s.renderer]);
    if (s.scene) rows.push(["scene", `${fmtInt(s.scene.instances)} instances, ${fmtInt(s.scene.instanced_triangles)} triangles`]);
    for (const [kind, n] of Object.entries(s.rays || {})) rows.push([`${kind} rays`, fmtInt(n)]);
    rows.push(["rays total", fmtInt(sum(s.rays))]);
    for (const [kind, n] of Object.entries(s.transfers || {})) {
      if (n) rows.push([`${kind} transfers`, `${fmtInt(n)} (${fmtBytes(s.bytes?.[kind] || 0)})`]);
    }
    rows.push(["transfers total", `${fmtInt(s.total_transfers || 0)} (${fmtBytes(s.total_bytes || 0)})`]);
    if (s.hops_histogram?.length) rows.push(["hops histogram", s.hops_histogram.join(" / ")]);
    for (const [k, v] of Object.entries(s.counters || {})) rows.push([k.replaceAll("_", " "), fmtInt(v)]);
    // What the proxy policy chose for each base mesh, and why (proxy and oracle jobs).
    for (const d of s.proxy_plan?.decisions || []) {
      const what = d.decision === "proxy" ? `proxy, width ${d.width}, ${(100 * d.accuracy).toFixed(2)}% held-out, ${fmtBytes(d.proxy_bytes)}` : d.decision;
      rows.push([`mesh ${d.name}`, `${what}: ${d.reason}`]);
    }
    if (TERMINAL.has(job.state)) {
      const base = await exactBaseline(job).catch(() => null);
      if (base?.stats) {
        const saved = base.stats.total_bytes - (s.total_bytes || 0);
        const pct = base.stats.total_bytes ? ` (${(100 * saved / base.stats.total_bytes).toFixed(1)}%)` : "";
        rows.push(["bytes saved vs exact", `${fmtBytes(saved)}${pct} against job ${shortId(base.id)}`]);
      }
    }
  }
  if (job.pixel_samples) rows.push(["samples per pixel", `${job.pixel_samples.min}–${job.pixel_samples.max}`]);
  $("#stats-table tbody").replaceChildren(...rows.map(([k, v]) => el("tr", {}, el("td", {}, k), el("td", {}, v))));
  drawPhaseChart(s?.phase_s || {});
}

function drawPhaseChart(phases) {
  const entries = Object.entries(phases).sort((a, b) => b[1] - a[1]);
  const box = $("#phase-chart");
  if (!entries.length) { box.textContent = "no timings yet"; return; }
  const NS = "http://www.w3.org/2000/svg";
  const barH = 18, gap = 6, labelW = 110, width = 420, max = entries[0][1] || 1;
  const svg = document.createElementNS(NS, "svg");
  svg.setAttribute("width", "100%");
  svg.setAttribute("viewBox", `0 0 ${width} ${entries.length * (barH + gap)}`);
  svg.id = "phase-svg";
  entries.forEach(([name, secs], i) => {
    const y = i * (barH + gap);
    const w = Math.max(1, (width - labelW - 70) * secs / max);
    const label = document.createElementNS(NS, "text");
    label.setAttribute("x", 0); label.setAttribute("y", y + 13); label.textContent = name;
    const rect = document.createElementNS(NS, "rect");
    Object.entries({ x: labelW, y, width: w, height: barH, fill: "#2f6fde", rx: 2 }).forEach(([k, v]) => rect.setAttribute(k, v));
    const value = document.createElementNS(NS, "text");
    value.setAttribute("x", labelW + w + 4); value.setAttribute("y", y + 13);
    value.textContent = `${secs.toFixed(3)} s`;
    svg.append(label, rect, value);
  });
  box.replaceChildren(svg);
}

function showJob(job) {
  current = job;
  $("#job-id").textContent = job.id;
  const state = $("#job-state");
  state.textContent = job.state;
  state.className = `state ${job.state}`;
  showProgress(job.progress);
  $("#job-error").textContent = job.error || "";
  $("#cancel-button").disabled = TERMINAL.has(job.state);
  showStats(job);
}

function openJob(id) {
  $("#job-image").removeAttribute("src");
  $("#png-link").href = `/v1/jobs/${id}/image.png`;
  $("#exr-link").href = `/v1/jobs/${id}/image.exr`;
  source = new EventSource(`/v1/jobs/${id}/events`);
  source.addEventListener("state", (ev) => {
    const job = JSON.parse(ev.data);
    showJob(job);
    if (job.passes_done > 0) refreshImage();
    if (TERMINAL.has(job.state)) { source.close(); source = null; }
  });
  source.addEventListener("tile", (ev) => {
    showProgress(JSON.parse(ev.data).progress);
    refreshImage();
  });
  source.addEventListener("end", () => { if (source) { source.close(); source = null; } });
  source.onerror = () => { $("#job-error").textContent = "event stream interrupted; retrying"; };
}

$("#cancel-button").addEventListener("click", async () => {
  try {
    showJob(await api(`/v1/jobs/${current.id}/cancel`, { method: "POST" }));
  } catch (e) {
    $("#job-error").textContent = e.message;
  }
});

// ------------------------------------------------------------------ routing

function route() {
  if (source) { source.close(); source = null; }
  clearInterval(listTimer);
  const m = location.hash.match(/^#\/jobs\/([0-9a-f]+)$/);
  $("#list-view").hidden = !!m;
  $("#job-view").hidden = !m;
  if (m) {
    openJob(m[1]);
  } else {
    refreshList();
    listTimer = setInterval(refreshList, LIST_POLL_MS);
  }
}

window.addEventListener("hashchange", route);
loadScenes().catch((e) => { $("#submit-error").textContent = e.message; });
route();
