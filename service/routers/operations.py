"""The routers for operating the service (logs, metrics, delete, linear pixels), gathered so
the app includes them in one line."""

from __future__ import annotations

from fastapi import APIRouter

from nprt.service.routers import job_files, logs, metrics

router = APIRouter()
for _sub in (logs.router, job_files.router, metrics.router):
    router.include_router(_sub)
