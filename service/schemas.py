"""REST schema families: JobCreate / JobPublic / JobsPublic and ScenePublic / ScenesPublic."""

from __future__ import annotations

from datetime import UTC, datetime
from functools import lru_cache
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator
from pydantic_core import to_json

from nprt.service.problems import Problem
from nprt.service.store import JobRecord
from nprt.workers.settings import RenderSettings

MAX_FRAME = 99_999  # nprt.scene.animation.MAX_FRAMES - 1
JobState = Literal["queued", "preparing", "running", "succeeded", "failed", "canceled"]


class FrameRange(BaseModel):
    """Frames first to last, inclusive; checked against the scene's frame count when the
    job loads it (a job past the last frame fails naming it)."""

    model_config = ConfigDict(extra="forbid")

    first: int = Field(ge=0, le=MAX_FRAME)
    last: int = Field(ge=0, le=MAX_FRAME)

    @model_validator(mode="after")
    def _ordered(self) -> FrameRange:
        if self.last < self.first:
            raise ValueError(f"last ({self.last}) is before first ({self.first})")
        return self


class JobCreate(RenderSettings):
    """A render request: the scene plus every RenderSettings field, with its constraints."""

    scene: str = Field(min_length=1, max_length=200, examples=["forest:tiny"],
                       description="demo name (forest, city, sculpture, windy; optional "
                                   ":small/:tiny) or the id of an uploaded scene")
    frames: FrameRange | None = Field(None, description="render these frames of an animated "
                                      "scene, one image each (GET /v1/jobs/{id}/frames/{f}"
                                      ".png); unset: one image of frame 0")

    def render_settings(self) -> RenderSettings:
        """Its RenderSettings fields, validated already (this model declares them with their
        constraints and validators): built without validating again, a fifth of an
        admission's Python time."""
        return RenderSettings.model_construct(**{k: getattr(self, k) for k in _SETTINGS})


_SETTINGS = tuple(RenderSettings.model_fields)


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
    frames: FrameRange | None = Field(None, description="the frames this job renders; "
                                      "each finished one at /v1/jobs/{id}/frames/{f}.png")

    @classmethod
    def from_record(cls, r: JobRecord, settings: RenderSettings | None = None) -> JobPublic:
        """settings: the record's settings validated already (the admission has them)."""
        if settings is None:
            settings = (_stored_settings(r.settings_json) if r.settings_json is not None
                        else r.settings)
        return cls(id=r.id, scene=r.scene, state=r.state, settings=settings,
                   progress=r.progress, passes_done=r.passes_done, passes_total=r.passes_total,
                   created_at=_time(r.created_at), started_at=_time(r.started_at),
                   finished_at=_time(r.finished_at), error=r.error, stats=r.stats,
                   pixel_samples=r.pixel_samples, cancel_requested=r.cancel_requested,
                   retries=r.retries,
                   frames=None if r.frames is None else FrameRange(first=r.frames[0],
                                                                   last=r.frames[1]))


def queued_job_json(rec: JobRecord, settings_json: str) -> bytes:
    """JobPublic.from_record(rec).model_dump_json() of a job just stored (queued, nothing
    done, no cancel, no retry) whose settings serialise to `settings_json`, in a tenth of
    its time: the admission's answer. The variable parts go through pydantic's serialiser;
    tests hold the two equal."""
    frames = b"null" if rec.frames is None else to_json(
        {"first": rec.frames[0], "last": rec.frames[1]})
    return b"".join((
        b'{"id":', to_json(rec.id), b',"scene":', to_json(rec.scene),
        b',"state":"queued","settings":', settings_json.encode(),
        b',"progress":0.0,"passes_done":0,"passes_total":', b"%d" % rec.passes_total,
        b',"created_at":', to_json(_time(rec.created_at)),
        b',"started_at":null,"finished_at":null,"error":null,"stats":null,'
        b'"pixel_samples":null,"cancel_requested":false,"retries":0,"frames":', frames, b"}"))


@lru_cache(maxsize=1024)
def _stored_settings(text: str) -> RenderSettings:
    """The validated settings of a stored job, once per distinct settings: validating them
    was 40 % of a job's answer, and a list or a burst repeats the same few. Shared, so
    never to be changed by a caller."""
    return RenderSettings.model_validate_json(text)


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
    404: "no such job or scene, or no such frame (not in the job, or not rendered yet)",
    409: "the request does not fit the job's state, or an Idempotency-Key reused for "
         "another request",
    413: "over NPRT_MAX_UPLOAD_BYTES or NPRT_MAX_EXTRACTED_BYTES, or a job body over 64 KiB",
    422: "invalid parameters, a job over a service limit (the detail names the field), or a "
         "body nested too deep",
    429: "NPRT_MAX_QUEUED_JOBS jobs are queued: retry after the Retry-After header's seconds "
         "(with the same Idempotency-Key)",
    503: "NPRT_MAX_WATCHERS event streams are open, or the job store is busy; try again "
         "after Retry-After when it is set",
}


def error_responses(*codes: int) -> dict:
    """`responses=` for a route: the error codes it can answer, in the OpenAPI schema."""
    return {c: {"model": Problem, "description": _ERRORS[c]} for c in codes}
