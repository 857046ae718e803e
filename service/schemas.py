"""REST schema families: JobCreate / JobPublic / JobsPublic and ScenePublic / ScenesPublic."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Literal

from pydantic import BaseModel, Field

from nprt.service.problems import Problem
from nprt.service.store import JobRecord
from nprt.workers.settings import RenderSettings

JobState = Literal["queued", "preparing", "running", "succeeded", "failed", "canceled"]


class JobCreate(RenderSettings):
    """A render request: the scene plus every RenderSettings field, with its constraints."""

    scene: str = Field(min_length=1, max_length=200, examples=["forest:tiny"],
                       description="demo name (forest, city, sculpture; optional :small/:tiny) "
                                   "or the id of an uploaded scene")

    def render_settings(self) -> RenderSettings:
        return RenderSettings.model_validate(self.model_dump(exclude={"scene"}))


class PixelSamples(BaseModel):
    min: int = Field(description="fewest samples any pixel received")
    max: int = Field(description="most samples any pixel received")


class JobPublic(BaseModel):
    id: str
    scene: str
    state: JobState
    settings: RenderSettings
    progress: float = Field(ge=0.0, le=1.0, description="passes_done / passes_total")
    passes_done: int = Field(ge=0)
    passes_total: int = Field(ge=0)
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    error: str | None = None
    stats: dict | None = Field(None, description="rays, transfers, bytes by kind; phase_s "
                                                 "in seconds; final stats add scene info")
    pixel_samples: PixelSamples | None = Field(None, description="set once succeeded")
    cancel_requested: bool = Field(False, description="a cancel is stored: the job ends "
                                                      "canceled at its next pass boundary")
    retries: int = Field(0, ge=0, description="times the job was re-queued from its "
                                              "checkpoint after losing a Ray node")

    @classmethod
    def from_record(cls, r: JobRecord) -> JobPublic:
        return cls(id=r.id, scene=r.scene, state=r.state, settings=r.settings,
                   progress=r.progress, passes_done=r.passes_done, passes_total=r.passes_total,
                   created_at=_time(r.created_at), started_at=_time(r.started_at),
                   finished_at=_time(r.finished_at), error=r.error, stats=r.stats,
                   pixel_samples=r.pixel_samples, cancel_requested=r.cancel_requested,
                   retries=r.retries)


class JobsPublic(BaseModel):
    data: list[JobPublic]
    count: int = Field(ge=0, description="all jobs matching the filter, not just this page")
    offset: int = Field(ge=0)
    limit: int = Field(ge=1)


class TileEvent(BaseModel):
    """The SSE `tile` event: one finished pass."""

    pass_index: int
    passes_total: int
    rect: tuple[int, int, int, int] = Field(description="x0, y0, x1, y1 pixels, half-open")
    sample0: int
    sample1: int
    progress: float = Field(ge=0.0, le=1.0)
    pixels: str | None = Field(None, description="with ?pixels=f16 only: base64 of the "
                               "tile's linear RGB so far, (h, w, 3) little-endian float16")


class ScenePublic(BaseModel):
    id: str = Field(description="sha256 of the upload, or the demo name")
    kind: Literal["demo", "glb", "gltf", "json", "zip"]
    filename: str | None = None
    entry: str | None = Field(None, description="the scene file inside the stored upload")
    size_bytes: int | None = Field(None, description="upload size, bytes")
    created_at: datetime | None = None
    summary: dict | None = Field(None, description="Scene.summary(): meshes, instances, "
                                                   "triangles, mesh bytes, lights")

    @classmethod
    def from_meta(cls, m: dict) -> ScenePublic:
        return cls(**{**m, "created_at": _time(m.get("created_at"))})


class ScenesPublic(BaseModel):
    data: list[ScenePublic]
    count: int


def _time(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, tz=UTC)


_ERRORS = {
    400: "a body that does not parse, or a malformed or unsafe upload (the detail names "
         "the zip member)",
    401: "missing or wrong bearer token (only when the server sets NPRT_API_TOKEN)",
    404: "no such job or scene",
    409: "the request does not fit the job's state, or an Idempotency-Key reused for "
         "another request",
    413: "over NPRT_MAX_UPLOAD_BYTES or NPRT_MAX_EXTRACTED_BYTES",
    422: "invalid parameters, or a job over a service limit (the detail names the field)",
    503: "NPRT_MAX_WATCHERS event streams are open; try again later",
}


def error_responses(*codes: int) -> dict:
    """`responses=` for a route: the error codes it can answer, in the OpenAPI schema."""
    return {c: {"model": Problem, "description": _ERRORS[c]} for c in codes}
