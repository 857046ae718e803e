"""The FastAPI app of one API worker: routers, error mapping, the dashboard, and a lifespan
that opens the job store and its event feed (and optionally the gRPC server). It renders
nothing: the scheduler process does (nprt.service.processes says who owns what)."""

from __future__ import annotations

import asyncio
import gc
import logging
import math
import os
import shutil
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.formparsers import MultiPartException

from nprt.service.admission import FastAdmission
from nprt.service.auth import TokenMiddleware
from nprt.service.bodyguard import JsonGuard
from nprt.service.config import ServiceSettings
from nprt.service.errors import BadUpload, ServiceError, redact_paths
from nprt.service.fastreads import FastReads
from nprt.service.jobapi import JobApi
from nprt.service.problems import describe_fields, document_problems, problem_response, type_name
from nprt.service.routers import jobs, operations, scenes
from nprt.service.scenes import SceneStore

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"
# Allocations (net) between young collections. At Python's 700, the objects of a burst's
# requests in flight set off a collection every few requests and were walked again as they
# aged: 11-14 us of a worker's CPU per admission (in process, bursts of 500); at 50,000
# none ran in 3,000 admissions. Cycles wait a little longer to be freed.
GC_YOUNG_THRESHOLD = 50_000


def create_app(settings: ServiceSettings | None = None, grpc_port: int | None = None,
               grpc_host: str = "127.0.0.1") -> FastAPI:
    """grpc_port None = REST only; 0 = any free port (see app.state.grpc_port)."""
    settings = settings or ServiceSettings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    roots = [str(settings.data_dir.absolute()), str(settings.data_dir.resolve())]

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # Uploads a killed process left half-spooled; no request is running yet.
        shutil.rmtree(settings.tmp_dir, ignore_errors=True)
        scene_store = SceneStore(settings)
        api = JobApi(settings, scene_store).start()
        app.state.settings, app.state.scenes, app.state.api = settings, scene_store, api
        grpc_thread = None
        if grpc_port is not None:
            from nprt.service.grpc_server import GrpcThread

            grpc_thread = GrpcThread(api, settings, grpc_host, grpc_port)
            app.state.grpc_port = await asyncio.to_thread(grpc_thread.start)
        # What is alive now lives as long as the worker (modules, schemas, the app): a full
        # collection walked all of it, 65-220 ms that every request of a burst waited for.
        gc.collect()
        gc.freeze()
        thresholds = gc.get_threshold()
        gc.set_threshold(GC_YOUNG_THRESHOLD, *thresholds[1:])
        log.info("nprt API worker %d up: data dir %s", os.getpid(), settings.data_dir)
        try:
            yield
        finally:
            gc.set_threshold(*thresholds)  # an embedding process gets its own back
            try:
                if grpc_thread is not None:
                    await asyncio.to_thread(grpc_thread.stop)
            finally:  # the store writer and event feed threads end even if that failed
                api.stop()

    # FastAPI's OpenTelemetry hooks asked for the global providers on every request (a
    # quarter of a polled read's CPU); the service exports Prometheus metrics instead.
    app = FastAPI(title="nprt render service", version="1", lifespan=lifespan,
                  telemetry={"tracing": False, "metrics": False, "logs": False,
                             "operation_spans": False},
                  description="Distributed path tracing jobs: upload scenes, submit renders, "
                              "follow tiles over SSE, fetch PNG/EXR. gRPC: protos/nprt.proto.")
    app.state.settings = settings
    # The last added runs first: the token is checked before the body guard reads a byte;
    # the polled reads (no token, no body) are answered before either.
    app.add_middleware(FastAdmission)
    app.add_middleware(JsonGuard)
    app.add_middleware(TokenMiddleware, token=settings.api_token)
    app.add_middleware(FastReads)
    app.include_router(scenes.router)
    app.include_router(jobs.router)
    app.include_router(operations.router)

    # Every error answer is RFC 9457 problem details (service/problems.py).
    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        retry = {"Retry-After": str(settings.retry_after_s)} if exc.retry_after else None
        return problem_response(exc.http_status, redact_paths(str(exc), roots),
                                type_=type_name(type(exc)), title=_title(type(exc)),
                                instance=request.url.path, headers=retry)

    @app.exception_handler(MultiPartException)
    async def multipart_error(request: Request, exc: MultiPartException) -> JSONResponse:
        return problem_response(400, f"bad multipart upload: {exc.message}",
                                type_=type_name(BadUpload), title=_title(BadUpload),
                                instance=request.url.path)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        """FastAPI's 422 with each field under `errors`, able to echo NaN and Infinity
        (strict JSON has neither)."""
        errors = _json_safe(exc.errors())
        return problem_response(422, describe_fields(errors), type_="urn:nprt:problem:"
                                "invalid-request", title="Invalid request",
                                instance=request.url.path, errors=errors)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        """Starlette's own answers (unknown route, wrong method, 401) in the same shape."""
        return problem_response(exc.status_code, str(exc.detail), instance=request.url.path,
                                headers=getattr(exc, "headers", None))

    openapi = app.openapi

    def openapi_with_problems() -> dict:
        if app.openapi_schema is None:
            document_problems(openapi())
        return app.openapi_schema

    app.openapi = openapi_with_problems

    @app.get("/", include_in_schema=False)
    async def dashboard() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    @app.get("/healthz", tags=["health"])
    async def healthz() -> dict:
        return {"status": "ok"}

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    return app


def app_from_env() -> FastAPI:
    """The app of one `nprt serve --workers N` worker: settings from NPRT_* variables, the
    gRPC address from NPRT_GRPC_HOST / NPRT_GRPC_PORT (every worker binds the same port;
    gRPC sets SO_REUSEPORT, so the kernel spreads connections over them)."""
    port = os.environ.get("NPRT_GRPC_PORT")
    return create_app(ServiceSettings(), grpc_port=int(port) if port else None,
                      grpc_host=os.environ.get("NPRT_GRPC_HOST", "127.0.0.1"))


def _title(cls: type) -> str:
    """`InvalidScene` -> `Invalid scene`: the problem type's summary."""
    return type_name(cls).removeprefix("urn:nprt:problem:").replace("-", " ").capitalize()


def _json_safe(errors) -> list:
    """Validation errors as strict JSON: non-finite floats as strings, undecodable bytes
    as their repr."""
    def fix(x):
        if isinstance(x, float) and not math.isfinite(x):  # as the client wrote it
            return "NaN" if math.isnan(x) else ("Infinity" if x > 0 else "-Infinity")
        if isinstance(x, bytes):
            return repr(x)
        if isinstance(x, dict):
            return {str(k): fix(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [fix(v) for v in x]
        return x

    return jsonable_encoder(fix(errors))
