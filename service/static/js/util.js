// Shared helpers: DOM building, the REST client with the bearer token, formatting.
"use strict";

export const TERMINAL = new Set(["succeeded", "failed", "canceled"]);
export const LIVE = new Set(["queued", "preparing", "running"]);
export const STATES = ["queued", "preparing", "running", "succeeded", "failed", "canceled"];
export const $ = (sel, root = document) => root.querySelector(sel);

const tokenInput = $("#token");
tokenInput.value = localStorage.getItem("nprt-token") || "";
tokenInput.addEventListener("change", () => localStorage.setItem("nprt-token", tokenInput.value));

export function authHeaders() {
  const t = tokenInput.value.trim();
  return t ? { Authorization: `Bearer ${t}` } : {};
}

// fetch + JSON, throwing Error("<status>: <detail>") on a non-2xx answer (an RFC 9457
// problem: its detail names each invalid field).
export async function api(path, options = {}) {
  const r = await fetch(path, { ...options, headers: { ...authHeaders(), ...(options.headers || {}) } });
  if (r.status === 204) return null;
  const body = r.headers.get("content-type")?.includes("json") ? await r.json() : await r.text();
  if (!r.ok) {
    const msg = (body && (body.detail || body.title)) || body;
    throw new Error(`${r.status}: ${msg}`);
  }
  return body;
}

export function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) if (v !== undefined && v !== null) e.setAttribute(k, v);
  for (const c of children) if (c !== null && c !== undefined) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}

export function svg(tag, attrs = {}, text) {
  const e = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}

export const fmtBytes = (n) => n >= 1 << 30 ? `${(n / (1 << 30)).toFixed(2)} GiB` : n >= 1 << 20 ? `${(n / (1 << 20)).toFixed(2)} MiB` : n >= 1024 ? `${(n / 1024).toFixed(1)} KiB` : `${n} B`;
export const fmtInt = (n) => Number(n).toLocaleString("en-US");
export const sum = (obj) => Object.values(obj || {}).reduce((a, b) => a + b, 0);
export const shortId = (id) => id.slice(0, 8);

export function fmtSeconds(s) {
  if (s === null || s === undefined) return "–";
  if (s < 60) return `${s.toFixed(s < 10 ? 2 : 1)} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
  return `${Math.floor(s / 3600)} h ${Math.round((s % 3600) / 60)} min`;
}

export function fmtAge(iso, now = Date.now()) {
  const s = (now - Date.parse(iso)) / 1000;
  if (s < 60) return `${Math.max(0, Math.round(s))} s ago`;
  if (s < 3600) return `${Math.round(s / 60)} min ago`;
  if (s < 86400) return `${Math.round(s / 3600)} h ago`;
  return `${Math.round(s / 86400)} d ago`;
}

// Seconds from start to finish, or to now while the job runs; null before it starts.
export function durationS(job, now = Date.now()) {
  if (!job.started_at) return null;
  const end = job.finished_at ? Date.parse(job.finished_at) : now;
  return Math.max(0, (end - Date.parse(job.started_at)) / 1000);
}

// "64×48 · 4 spp · proxy ×2": what a job renders, in one line.
export function settingsSummary(s) {
  const where = s.shards ? `${s.mode} ×${s.shards}` : `${s.mode} · reference`;
  return `${s.width}×${s.height} · ${s.spp} spp · ${where}`;
}

export function progressBar(fraction) {
  const pct = Math.round(fraction * 100);
  const fill = el("div", { class: "fill", style: `width:${pct}%`, role: "progressbar", "aria-valuenow": pct });
  return el("div", { class: "bar" }, fill, el("span", {}, `${pct}%`));
}

export const sceneLabel = (scene) => (scene.length > 40 ? shortId(scene) : scene);
