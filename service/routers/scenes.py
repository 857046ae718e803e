"""/v1/scenes: upload (GLB, glTF, JSON, or zip of a JSON scene with its meshes), list, get."""

from __future__ import annotations

import hashlib
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from starlette.formparsers import MultiPartParser

from nprt.service.deps import ScenesDep, SettingsDep, TokenDep
from nprt.service.errors import BadUpload, TooLarge
from nprt.service.problems import Problem
from nprt.service.scenes import demo_names
from nprt.service.schemas import ScenePublic, ScenesPublic, error_responses

router = APIRouter(prefix="/v1/scenes", tags=["scenes"])

_UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "description": "the file as the raw body, or multipart/form-data with a `file` field",
        "content": {
            t: {"schema": {"type": "string", "format": "binary"}}
            for t in ("model/gltf-binary", "model/gltf+json", "application/zip",
                      "application/json", "application/octet-stream")
        } | {"multipart/form-data": {"schema": {
            "type": "object", "required": ["file"],
            "properties": {"file": {"type": "string", "format": "binary"}}}}},
    }
}


async def _limited(stream: AsyncIterator[bytes], max_bytes: int) -> AsyncIterator[bytes]:
    """Pass chunks through, refusing once more than max_bytes arrived (Content-Length
    can be absent with chunked encoding, or lie)."""
    seen = 0
    async for chunk in stream:
        seen += len(chunk)
        if seen > max_bytes:
            raise TooLarge(f"upload is larger than the limit of {max_bytes} bytes")
        yield chunk


async def _spool(request: Request, dest: Path, max_bytes: int) -> tuple[str, int, str | None]:
    """Write the uploaded file to dest; returns (sha256 hex, bytes, multipart filename)."""
    body = _limited(request.stream(), max_bytes)
    digest, size, filename = hashlib.sha256(), 0, None
    with dest.open("wb") as out:
        if request.headers.get("content-type", "").startswith("multipart/form-data"):
            form = await MultiPartParser(request.headers, body, max_files=1, max_fields=8).parse()
            upload = form.get("file")
            if upload is None or isinstance(upload, str):
                raise BadUpload("multipart upload needs a file field named 'file'")
            filename = upload.filename
            while chunk := await upload.read(1 << 20):
                digest.update(chunk)
                size += len(chunk)
                out.write(chunk)
            await form.close()
        else:
            async for chunk in body:
                digest.update(chunk)
                size += len(chunk)
                out.write(chunk)
    if size == 0:
        raise BadUpload("empty upload")
    return digest.hexdigest(), size, filename


@router.post("", status_code=status.HTTP_201_CREATED, dependencies=[TokenDep],
             openapi_extra=_UPLOAD_BODY,
             responses={200: {"model": ScenePublic,
                              "description": "identical upload already stored"}}
             | error_responses(400, 401, 413)
             | {422: {"model": Problem,
                      "description": "the scene does not load (SceneError message)"}})
async def upload_scene(request: Request, response: Response, scenes: ScenesDep,
                       settings: SettingsDep,
                       filename: Annotated[str | None, Query(max_length=200, description=
                                           "original file name, for raw-body uploads")] = None
                       ) -> ScenePublic:
    """Store a scene content-addressed; its id is the sha256 of the uploaded bytes."""
    max_bytes = settings.max_upload_bytes
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        raise TooLarge(f"upload of {declared} bytes is larger than the limit of {max_bytes}")
    with tempfile.TemporaryDirectory(prefix="upload-", dir=settings.tmp_dir) as tmp:
        path = Path(tmp) / "upload"
        sha, size, form_name = await _spool(request, path, max_bytes)
        meta, created = await run_in_threadpool(scenes.ingest, path, sha, size,
                                                 form_name or filename)
    if not created:
        response.status_code = status.HTTP_200_OK
    response.headers["Location"] = f"/v1/scenes/{sha}"
    return ScenePublic.from_meta(meta)


@router.get("")
async def list_scenes(scenes: ScenesDep) -> ScenesPublic:
    """Demo scenes (by name; sizes ':small', ':tiny') and uploaded scenes, newest first."""
    demos = [ScenePublic(id=name, kind="demo") for name in demo_names()]
    uploads = [ScenePublic.from_meta(m) for m in await run_in_threadpool(scenes.uploads)]
    return ScenesPublic(data=demos + uploads, count=len(demos) + len(uploads))


@router.get("/{scene_id}", responses=error_responses(404))
async def get_scene(scene_id: str, scenes: ScenesDep) -> ScenePublic:
    """One scene with its summary (a demo is built on first request, then cached)."""
    return ScenePublic.from_meta(await run_in_threadpool(scenes.describe, scene_id))
