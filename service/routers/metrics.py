"""GET /metrics: Prometheus text exposition of the job service and of this process."""

from __future__ import annotations

import time

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.process_collector import ProcessCollector

from nprt.service.metrics import JobMetrics

router = APIRouter(tags=["health"])
# Counters count the jobs that finished after this: about when the service started.
LOADED_AT_S = time.time()


def _registry(request: Request) -> CollectorRegistry:
    """One registry per app (tests run several apps in one process), made on first scrape."""
    state = request.app.state
    if getattr(state, "metrics_registry", None) is None:
        registry = CollectorRegistry()
        registry.register(JobMetrics(state.api.store, since_s=LOADED_AT_S))
        ProcessCollector(registry=registry)
        state.metrics_registry = registry
    return state.metrics_registry


@router.get("/metrics", response_class=Response, responses={200: {
    "content": {CONTENT_TYPE_LATEST.split(";")[0]: {}},
    "description": "Prometheus text format: nprt_jobs{state}, nprt_queue_length, "
                   "nprt_rays_per_second, nprt_rays_total{kind}, nprt_moved_bytes_total{kind}, "
                   "nprt_shard_busy_fraction, nprt_prepare_seconds, "
                   "nprt_proxy_train_seconds_total, process_*"}})
async def metrics(request: Request) -> Response:
    body = await run_in_threadpool(generate_latest, _registry(request))
    return Response(body, media_type=CONTENT_TYPE_LATEST)
