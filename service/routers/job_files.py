"""DELETE /v1/jobs/{id}, /v1/jobs/{id}/pixels (the linear image for the dashboard) and
/v1/jobs/{id}/frames/{f}.png|exr (each finished frame of a frames job)."""

from __future__ import annotations

import tempfile
from pathlib import Path as FilePath
from typing import Annotated

from fastapi import APIRouter, Path, Response, status
from fastapi.concurrency import run_in_threadpool

from nprt.service import images
from nprt.service.deps import ApiDep, TokenDep
from nprt.service.schemas import MAX_FRAME, error_responses
from nprt.workers.film import read_exr

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT, dependencies=[TokenDep],
               responses=error_responses(401, 404, 409))
async def delete_job(job_id: str, api: ApiDep) -> Response:
    """Forget a finished, failed or canceled job: its record, image, checkpoint and log."""
    await run_in_threadpool(api.delete, job_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def linear_pixels(api, job_id: str):
    """((h, w, 3) float32 linear, partial): the job's image as EXR decoded."""
    data, partial = api.image(job_id, "exr")
    with tempfile.TemporaryDirectory(prefix="nprt-px-") as d:
        path = FilePath(d) / "image.exr"
        path.write_bytes(data)
        return read_exr(path), partial


@router.get("/{job_id}/pixels", response_class=Response, responses={200: {
    "content": {"application/octet-stream": {}},
    "description": "linear RGB, row-major (h, w, 3) little-endian float16; headers "
                   "X-Nprt-Width, X-Nprt-Height, X-Nprt-Partial. 404 before the first pass."}}
            | error_responses(404))
async def get_pixels(job_id: str, api: ApiDep) -> Response:
    img, partial = await run_in_threadpool(linear_pixels, api, job_id)
    h, w = img.shape[:2]
    return Response(images.f16_bytes(img), media_type="application/octet-stream",
                    headers={"X-Nprt-Width": str(w), "X-Nprt-Height": str(h),
                             "X-Nprt-Partial": str(partial).lower(),
                             "Cache-Control": "no-store"})



FrameDep = Annotated[int, Path(ge=0, le=MAX_FRAME, description="frame number")]


async def _frame(api, job_id: str, frame: int, fmt: str, media: str) -> Response:
    data = await run_in_threadpool(api.frame_image, job_id, frame, fmt)
    return Response(data, media_type=media, headers={"Cache-Control": "no-store"})


@router.get("/{job_id}/frames/{frame}.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "sRGB PNG of one "
                             "finished frame of a frames job"}} | error_responses(404))
async def get_frame_png(job_id: str, frame: FrameDep, api: ApiDep) -> Response:
    return await _frame(api, job_id, frame, "png", "image/png")


@router.get("/{job_id}/frames/{frame}.exr", response_class=Response,
            responses={200: {"content": {"image/x-exr": {}}, "description": "linear float32 "
                             "OpenEXR of one finished frame of a frames job"}}
            | error_responses(404))
async def get_frame_exr(job_id: str, frame: FrameDep, api: ApiDep) -> Response:
    return await _frame(api, job_id, frame, "exr", "image/x-exr")
