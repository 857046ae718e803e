"""The FastAPI app: routers, error mapping, the dashboard, and a lifespan that runs the job
manager (and optionally the gRPC server) in the same process."""

from __future__ import annotations

import logging
import math
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

from nprt.service.auth import TokenMiddleware
from nprt.service.config import ServiceSettings
from nprt.service.errors import (
    BadUpload,
    Conflict,
    InvalidJob,
    InvalidScene,
    NotFound,
    ServiceError,
    TooLarge,
    TooManyWatchers,
    UnknownScene,
    redact_paths,
)
from nprt.service.manager import JobManager
from nprt.service.problems import describe_fields, document_problems, problem_response, type_name
from nprt.service.routers import jobs, operations, scenes
from nprt.service.scenes import SceneStore

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"
_STATUS = {NotFound: 404, Conflict: 409, BadUpload: 400, TooLarge: 413, InvalidScene: 422,
           InvalidJob: 422, UnknownScene: 422, TooManyWatchers: 503}


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
        manager = JobManager(settings, scene_store)
        app.state.settings, app.state.scenes, app.state.manager = settings, scene_store, manager
        manager.start()
        grpc_server = None
        if grpc_port is not None:
            from nprt.service.grpc_server import start_grpc_server

            grpc_server, app.state.grpc_port = await start_grpc_server(manager, settings,
                                                                       grpc_host, grpc_port)
        log.info("nprt service up: data dir %s, %d job slot(s)", settings.data_dir,
                 settings.max_concurrent_jobs)
        try:
            yield
        finally:
            if grpc_server is not None:
                await grpc_server.stop(1.0)
            manager.stop()

    app = FastAPI(title="nprt render service", version="1", lifespan=lifespan,
                  description="Distributed path tracing jobs: upload scenes, submit renders, "
                              "follow tiles over SSE, fetch PNG/EXR. gRPC: protos/nprt.proto.")
    app.state.settings = settings
    app.add_middleware(TokenMiddleware, token=settings.api_token)
    app.include_router(scenes.router)
    app.include_router(jobs.router)
    app.include_router(operations.router)

    # Every error answer is RFC 9457 problem details (service/problems.py).
    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return problem_response(_STATUS.get(type(exc), 400), redact_paths(str(exc), roots),
                                type_=type_name(type(exc)), title=_title(type(exc)),
                                instance=request.url.path)

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
