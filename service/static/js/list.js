// The job list (state filter, sort, paging, age, duration, settings), the submit form and
// scene upload.
"use strict";

import { $, api, durationS, el, fmtAge, fmtInt, fmtSeconds, progressBar, sceneLabel, settingsSummary, shortId } from "./util.js";

const POLL_MS = 2000;
// The API pages newest first; sorting any other way covers the newest FETCH_LIMIT jobs.
const FETCH_LIMIT = 500;
const SORTS = {
  newest: (a, b) => Date.parse(b.created_at) - Date.parse(a.created_at),
  oldest: (a, b) => Date.parse(a.created_at) - Date.parse(b.created_at),
  longest: (a, b) => (durationS(b) ?? -1) - (durationS(a) ?? -1),
  scene: (a, b) => a.scene.localeCompare(b.scene),
  state: (a, b) => a.state.localeCompare(b.state),
  progress: (a, b) => b.progress - a.progress,
};

let timer = null;
let page = 0;

export function openList() {
  refresh();
  timer = setInterval(refresh, POLL_MS);
}

export function closeList() {
  clearInterval(timer);
}

function pageSize() { return Number($("#page-size").value); }

async function refresh() {
  const state = $("#state-filter").value;
  try {
    const jobs = await api(`/v1/jobs?limit=${FETCH_LIMIT}${state ? `&state=${state}` : ""}`);
    const rows = jobs.data.sort(SORTS[$("#sort").value]);
    const pages = Math.max(1, Math.ceil(rows.length / pageSize()));
    page = Math.min(page, pages - 1);
    const shown = rows.slice(page * pageSize(), (page + 1) * pageSize());
    const now = Date.now();
    $("#job-count").textContent = `(${fmtInt(jobs.count)}${state ? ` ${state}` : ""})`;
    $("#page-info").textContent = `page ${page + 1} of ${pages}` + (jobs.count > FETCH_LIMIT ? ` · sorting covers the newest ${FETCH_LIMIT}` : "");
    $("#prev-page").disabled = page === 0;
    $("#next-page").disabled = page >= pages - 1;
    $("#job-table tbody").replaceChildren(...shown.map((j) => el("tr", { "data-job": j.id },
      el("td", {}, el("a", { href: `#/jobs/${j.id}` }, shortId(j.id))),
      el("td", { title: j.scene }, sceneLabel(j.scene)),
      el("td", { class: "settings" }, settingsSummary(j.settings)),
      el("td", {}, el("span", { class: `state ${j.state}` }, j.state)),
      el("td", {}, progressBar(j.progress)),
      el("td", { class: "age", title: new Date(j.created_at).toLocaleString() }, fmtAge(j.created_at, now)),
      el("td", { class: "duration" }, fmtSeconds(durationS(j, now))))));
  } catch (e) {
    $("#job-count").textContent = `(${e.message})`;
  }
}

for (const id of ["#state-filter", "#sort", "#page-size"]) {
  $(id).addEventListener("change", () => { page = 0; refresh(); });
}
$("#prev-page").addEventListener("click", () => { page = Math.max(0, page - 1); refresh(); });
$("#next-page").addEventListener("click", () => { page += 1; refresh(); });

// ------------------------------------------------------------------ submit and upload

export async function loadScenes(select) {
  const scenes = await api("/v1/scenes");
  const box = $("#scene-select");
  box.replaceChildren(...scenes.data.map((s) =>
    el("option", { value: s.id, "data-kind": s.kind }, s.kind === "demo" ? s.id : `${s.summary?.name || s.filename} (${shortId(s.id)})`)));
  if (select) box.value = select;
  sceneChanged();
}

function sceneChanged() {
  const demo = $("#scene-select").selectedOptions[0]?.dataset.kind === "demo";
  $("#size-label").hidden = !demo; // sizes are a demo's only
}

function modeChanged() {
  const mode = $("select[name=mode]").value;
  for (const e of document.querySelectorAll(".proxy-knob")) e.hidden = mode !== "proxy";
}

$("#scene-select").addEventListener("change", sceneChanged);
$("select[name=mode]").addEventListener("change", modeChanged);
modeChanged();

$("#submit-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const f = new FormData(ev.target);
  const kind = $("#scene-select").selectedOptions[0]?.dataset.kind;
  const size = f.get("size");
  const body = { scene: kind === "demo" && size ? `${f.get("scene")}:${size}` : f.get("scene"), mode: f.get("mode") };
  for (const k of ["width", "height", "spp", "bounces", "shadow_rays", "shards", "tile_size", "spp_per_pass", "seed"]) {
    body[k] = Number(f.get(k));
  }
  if (f.get("byte_slack") !== "") body.byte_slack = Number(f.get("byte_slack"));
  if (body.mode === "proxy") {
    // Hand-set bands, where given, replace the accuracy target (workers/settings.py).
    body.proxy = { check: f.get("check") === "on" };
    if (f.get("accuracy")) body.proxy.accuracy = f.get("accuracy");
    for (const k of ["band", "shadow_band"]) if (f.get(k) !== "") body.proxy[k] = Number(f.get(k));
  }
  // A frame range when either end is given (one end alone: that frame); the server
  // checks it against the scene's frame count.
  const first = f.get("frame_first"), last = f.get("frame_last");
  if (first !== "" || last !== "") {
    body.frames = { first: Number(first !== "" ? first : last), last: Number(last !== "" ? last : first) };
  }
  $("#submit-error").textContent = "";
  try {
    const job = await api("/v1/jobs", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    location.hash = `#/jobs/${job.id}`;
  } catch (e) {
    $("#submit-error").textContent = e.message;
  }
});

$("#upload-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const file = $("#upload-file").files[0];
  const status = $("#upload-status");
  if (!file) { status.textContent = "choose a .glb, .gltf, .json or .zip file first"; return; }
  const form = new FormData();
  form.append("file", file);
  status.textContent = `uploading ${file.name}…`;
  status.className = "muted";
  try {
    const scene = await api("/v1/scenes", { method: "POST", body: form });
    const s = scene.summary || {};
    await loadScenes(scene.id); // selected before the status says so (the page test reads it)
    status.textContent = `uploaded ${file.name} as scene ${shortId(scene.id)}: ${fmtInt(s.instances ?? 0)} instances of ${fmtInt(s.base_meshes ?? 0)} meshes`;
  } catch (e) {
    status.textContent = e.message;
    status.className = "error";
  }
});
