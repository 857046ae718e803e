// The live log view: follows /v1/jobs/{id}/logs?follow=1 (SSE) and hands each line on.
"use strict";

import { el } from "./util.js";

const MAX_LINES = 2000; // the view keeps the newest lines only

export class LogView {
  constructor(pre, status) {
    this.pre = pre;
    this.status = status;
    this.source = null;
  }

  // onLine(text) sees every line, e.g. to explain what a preparing job is doing.
  open(jobId, onLine) {
    this.close();
    this.pre.replaceChildren();
    this.status.textContent = "following";
    this.source = new EventSource(`/v1/jobs/${jobId}/logs?follow=1`);
    this.source.addEventListener("log", (ev) => {
      const stick = this.pre.scrollTop + this.pre.clientHeight >= this.pre.scrollHeight - 4;
      const level = (ev.data.match(/ (DEBUG|INFO|WARNING|ERROR|CRITICAL) /) || [])[1] || "INFO";
      this.pre.append(el("div", { class: `log-line ${level.toLowerCase()}` }, ev.data));
      while (this.pre.childElementCount > MAX_LINES) this.pre.firstElementChild.remove();
      if (stick) this.pre.scrollTop = this.pre.scrollHeight;
      onLine?.(ev.data);
    });
    this.source.addEventListener("end", (ev) => {
      this.status.textContent = `complete (job ${ev.data})`;
      if (!this.pre.childElementCount) this.pre.append(el("div", { class: "muted" }, "(the job logged nothing)"));
      this.close();
    });
    this.source.onerror = () => { this.status.textContent = "reconnecting…"; };
  }

  close() {
    if (this.source) this.source.close();
    this.source = null;
  }
}
