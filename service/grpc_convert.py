"""Conversions between protos/nprt.proto messages and the service's own types."""

from __future__ import annotations

import numpy as np
from google.protobuf import struct_pb2

from nprt.protos import nprt_pb2 as pb
from nprt.service import images
from nprt.service.store import JobRecord
from nprt.workers.settings import ProxySettings, RenderSettings

STATE_TO_PB = {
    "queued": pb.JOB_STATE_QUEUED, "preparing": pb.JOB_STATE_PREPARING,
    "running": pb.JOB_STATE_RUNNING, "succeeded": pb.JOB_STATE_SUCCEEDED,
    "failed": pb.JOB_STATE_FAILED, "canceled": pb.JOB_STATE_CANCELED,
}
_SETTINGS_FIELDS = ("width", "height", "spp", "bounces", "shadow_rays", "seed",
                    "russian_roulette", "mode", "shards", "tile_size", "spp_per_pass",
                    "byte_slack")
_PROXY_FIELDS = ("threshold", "band", "accuracy_target", "shadow_band", "width", "steps",
                 "accuracy", "check", "internal_margin", "internal_ambiguous")


def settings_from_pb(msg: pb.RenderSettings) -> RenderSettings:
    """Unset optional fields take RenderSettings' defaults; pydantic.ValidationError if bad."""
    d = {f: getattr(msg, f) for f in _SETTINGS_FIELDS if msg.HasField(f)}
    if msg.HasField("proxy"):
        d["proxy"] = {f: getattr(msg.proxy, f) for f in _PROXY_FIELDS if msg.proxy.HasField(f)}
    return RenderSettings.model_validate(d)


def settings_to_pb(s: dict) -> pb.RenderSettings:
    rs = RenderSettings.model_validate(s)
    proxy: ProxySettings = rs.proxy
    return pb.RenderSettings(**{f: getattr(rs, f) for f in _SETTINGS_FIELDS},
                             proxy=pb.ProxySettings(**{
                                 k: str(v) if k == "accuracy" else v
                                 for k, v in proxy.model_dump(exclude_none=True).items()}))


def job_to_pb(r: JobRecord) -> pb.Job:
    stats = struct_pb2.Struct()
    if r.stats:
        stats.update(r.stats)
    return pb.Job(id=r.id, scene=r.scene, state=STATE_TO_PB[r.state],
                  settings=settings_to_pb(r.settings), passes_done=r.passes_done,
                  passes_total=r.passes_total, progress=r.progress, error=r.error or "",
                  created_at_unix_s=r.created_at, started_at_unix_s=r.started_at or 0.0,
                  finished_at_unix_s=r.finished_at or 0.0, stats=stats,
                  cancel_requested=r.cancel_requested, retries=r.retries,
                  frames=None if r.frames is None else pb.FrameRange(first=r.frames[0],
                                                                     last=r.frames[1]))


# Room for the Tile's other fields inside the message limit.
_TILE_OVERHEAD_BYTES = 1024


def tile_to_pb(ev: dict, fmt: int, max_bytes: int) -> pb.Tile:
    """A Tile message; pixels are dropped (format NONE) when they would not fit max_bytes."""
    x0, y0, x1, y1 = ev["rect"]
    rgb: np.ndarray = ev["rgb"]  # (th, tw, 3) float32 linear
    if fmt == pb.TILE_FORMAT_PNG:
        pixels = images.png_bytes(rgb)
    elif fmt == pb.TILE_FORMAT_RGB_F32:
        pixels = np.ascontiguousarray(rgb, dtype="<f4").tobytes()
    else:
        pixels = b""
    if len(pixels) > max_bytes - _TILE_OVERHEAD_BYTES:
        fmt, pixels = pb.TILE_FORMAT_NONE, b""
    return pb.Tile(pass_index=ev["pass_index"], passes_total=ev["passes_total"],
                   rect=pb.Rect(x0=x0, y0=y0, x1=x1, y1=y1), sample0=ev["sample0"],
                   sample1=ev["sample1"], progress=ev["progress"], format=fmt, pixels=pixels)
