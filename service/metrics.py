"""Prometheus metrics of the job service, computed at scrape time from the job store:
jobs by state, queue length, rays and bytes moved, shard busy fractions, preparation and
proxy training time."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    SummaryMetricFamily,
)
from prometheus_client.registry import Collector

from nprt.service.store import TERMINAL, JobRecord, JobStore

# Jobs finished this long before a scrape are still read again by it: a job's finish time
# is taken a moment before its row is written.
FINISH_MARGIN_S = 60.0
BUSY_BUCKETS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
_COUNTED = ("rays", "transfers", "bytes")  # per-kind stats dicts summed into counters


class JobMetrics(Collector):
    """Counters cover the jobs that ran while this process was up: each scrape adds what
    every active or just-finished job did since the previous scrape."""

    def __init__(self, store: JobStore, since_s: float | None = None):
        self.store = store
        self._lock = threading.Lock()
        self._since_s = time.time() if since_s is None else since_s
        self._counted: dict[str, dict[tuple[str, str], float]] = {}
        self._finished: dict[str, float] = {}  # job id -> finished_at, for jobs observed
        self._totals: dict[tuple[str, str], float] = defaultdict(float)
        self._busy_counts = [0] * len(BUSY_BUCKETS)
        self._busy_sum, self._busy_n = 0.0, 0
        self._last_shards: list[dict] = []
        self._prepare: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])  # mode -> n, s
        self._proxy_train_s: dict[str, float] = {}  # proxy (mesh hash, width) -> seconds
        self._rate = 0.0

    # ------------------------------------------------------------ bookkeeping

    def _update(self) -> None:
        now = time.time()
        jobs = self.store.active_or_finished_since(self._since_s)
        self._rate = 0.0
        for rec in jobs:
            self._add_work(rec)
            if rec.state in ("preparing", "running") and rec.started_at and rec.stats:
                self._rate += sum(rec.stats.get("rays", {}).values()) / max(
                    now - rec.started_at, 1e-3)
            if rec.state in TERMINAL and rec.id not in self._finished:
                self._finished[rec.id] = rec.finished_at or now
                self._observe_finished(rec)
        self._since_s = now - FINISH_MARGIN_S
        for job_id in [j for j, t in self._finished.items() if t < self._since_s]:
            del self._finished[job_id]
            self._counted.pop(job_id, None)

    def _add_work(self, rec: JobRecord) -> None:
        seen = self._counted.setdefault(rec.id, {})
        for family in _COUNTED:
            for kind, value in ((rec.stats or {}).get(family) or {}).items():
                delta = float(value) - seen.get((family, kind), 0.0)
                if delta > 0:  # a resumed job restarts from its checkpoint's lower count
                    self._totals[(family, kind)] += delta
                    seen[(family, kind)] = float(value)

    def _observe_finished(self, rec: JobRecord) -> None:
        stats = rec.stats or {}
        shards = stats.get("shard_stats") or []
        for shard in shards:
            f = float(shard.get("busy_fraction", 0.0))
            self._busy_sum += f
            self._busy_n += 1
            for i, le in enumerate(BUSY_BUCKETS):
                if f <= le:
                    self._busy_counts[i] += 1
        if shards:
            self._last_shards = shards
        if "prepare_s" in stats and not stats.get("warm_pool"):
            p = self._prepare[rec.settings.get("mode", "exact")]
            p[0] += 1
            p[1] += float(stats["prepare_s"])
        for d in (stats.get("proxy_plan") or {}).get("decisions", []):
            if d.get("train_s") is not None and rec.settings.get("mode") == "proxy":
                self._proxy_train_s.setdefault(f"{d['content_hash']}:{d['width']}",
                                               float(d["train_s"]))

    # ------------------------------------------------------------ exposition

    def collect(self):
        counts = self.store.counts_by_state()
        with self._lock:
            self._update()
            yield from self._families(counts)

    def _families(self, counts: dict[str, int]):
        g = GaugeMetricFamily("nprt_jobs", "Jobs in the store by state", labels=["state"])
        for state, n in counts.items():
            g.add_metric([state], n)
        yield g
        yield GaugeMetricFamily("nprt_queue_length", "Jobs queued, waiting for a job slot",
                                value=counts.get("queued", 0))
        yield GaugeMetricFamily(
            "nprt_rays_per_second", "Rays per second of the running jobs, summed; each job's "
            "rays so far over the seconds since it started", value=self._rate)
        for family, name, doc in (
                ("rays", "nprt_rays", "Rays traced by jobs of this process, by kind"),
                ("transfers", "nprt_transfers", "Ray batches moved between shards, by kind"),
                ("bytes", "nprt_moved_bytes", "Bytes moved between shards, by kind")):
            c = CounterMetricFamily(name, doc, labels=["kind"])
            for (fam, kind), v in sorted(self._totals.items()):
                if fam == family:
                    c.add_metric([kind], v)
            yield c
        cumulative = list(self._busy_counts)
        yield HistogramMetricFamily(
            "nprt_shard_busy_fraction", "Busy fraction (seconds working over the job's wall "
            "time) of each shard of each finished sharded job",
            buckets=[(str(le), n) for le, n in zip(BUSY_BUCKETS, cumulative, strict=True)]
            + [("+Inf", self._busy_n)], sum_value=self._busy_sum)
        last = GaugeMetricFamily("nprt_last_job_shard_busy_fraction",
                                 "Busy fraction of each shard of the last finished sharded job",
                                 labels=["shard", "node"])
        for s in self._last_shards:
            last.add_metric([str(s.get("shard")), str(s.get("node") or "")],
                            float(s.get("busy_fraction", 0.0)))
        yield last
        prep = SummaryMetricFamily("nprt_prepare_seconds", "Preparation of jobs that started "
                                   "a shard pool (partition, proxies fetched or trained, actors)",
                                   labels=["mode"])
        for mode, (n, total) in sorted(self._prepare.items()):
            prep.add_metric([mode], count_value=n, sum_value=total)
        yield prep
        yield CounterMetricFamily(
            "nprt_proxy_train_seconds", "Training seconds of the distinct proxies that "
            "finished proxy jobs used, once per proxy, as recorded when each was trained "
            "(a proxy from the cache counts its original training)",
            value=sum(self._proxy_train_s.values()))
