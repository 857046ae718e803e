// nprt dashboard entry: hash routing between the job list (#/) and a job page (#/jobs/<id>).
"use strict";

import { closeJob, openJob } from "./js/job.js";
import { closeList, loadScenes, openList } from "./js/list.js";
import { $ } from "./js/util.js";

function route() {
  closeJob();
  closeList();
  const m = location.hash.match(/^#\/jobs\/([0-9a-f]+)$/);
  $("#list-view").hidden = !!m;
  $("#job-view").hidden = !m;
  if (m) openJob(m[1]);
  else openList();
}

window.addEventListener("hashchange", route);
loadScenes().catch((e) => { $("#submit-error").textContent = e.message; });
route();
