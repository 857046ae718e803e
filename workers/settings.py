"""Render settings: one validated pydantic model shared by the CLI, REST, gRPC and workers."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from nprt.proxies.accuracy import parse_accuracy
from nprt.proxies.config import ProxyConfig
from nprt.scene.partition import BYTE_SLACK

Mode = Literal["exact", "proxy", "oracle"]


class ProxySettings(BaseModel):
    """The speed/accuracy knobs of the proxy traversal (DESIGN.md, "Traversal policies").

    `accuracy` (a PSNR against exact, or "exact") picks each proxy's bands from its own
    held-out error curve (nprt.proxies.accuracy); giving `band` or `shadow_band` instead
    sets them by hand for every proxy (accuracy then defaults to None)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    accuracy: float | Literal["exact"] | None = Field(
        40.0, description="what the job needs: a PSNR in dB against exact ('40dB' or 40), "
                          "or 'exact'; null: the hand-set band and shadow_band")
    check: bool = Field(False, description="after the render, render 1/64 of the pixels (8x8 "
                                           "blocks) exactly and report the measured PSNR "
                                           "with its 95 % interval beside the target")
    threshold: float | None = Field(
        None, ge=0.0, le=1.0,
        description="visibility at or above this is a hit; unset: each proxy's own threshold, "
                    "calibrated on held-out rays when it was trained")
    # 0.4 trusts only visibilities outside (threshold - 0.4, threshold + 0.4): measured at
    # K = 4 on the demos, 0.1 gave 43.5-44.7 dB against exact and 0.4 gives 45.4-48 dB for
    # 2-5 % more ray bytes (bench/README.md, "Confidence band").
    band: float = Field(0.4, ge=0.0, le=1.0,
                        description="secondary rays: a box entered before the closest confident "
                                    "hit with |visibility - threshold| < band is settled "
                                    "exactly, on its own shard")
    shadow_band: float = Field(
        0.0, ge=0.0, le=1.0,
        description="shadow rays: |visibility - threshold| < shadow_band falls back to exact "
                    "forwarding; 0 (the paper): every shadow ray is decided where it was made")
    accuracy_target: float = Field(0.97, gt=0.5, le=1.0,
                                   description="held-out visibility accuracy a width must reach")
    width: Literal[16, 32, 64, 128, 256] | None = Field(
        None, description="proxy width N for every mesh; unset: the narrowest of 16/32/64 "
                          "that reaches accuracy_target, or where none does, the narrowest "
                          "that the most accurate does not lead by more than 2 standard "
                          "errors of the held-out estimate")
    steps: int = Field(ProxyConfig.steps, ge=2, le=10_000_000,
                       description="training budget per proxy (both nets), optimiser steps; "
                                   "the same steps give the same proxy bytes, and the shipped "
                                   "proxies are trained at the default")
    # Internal case, secondary rays: the depth net cannot tell on which side of the origin a
    # surface lies when it is predicted within this fraction of the proxy's held-out
    # 90th-percentile depth error of it (bench/README.md, "The unsure zone around the origin").
    internal_margin: float = Field(0.5, ge=0.0, le=10.0,
                                   description="unsure zone of an internal answer around the "
                                               "origin, in the proxy's p90 depth errors")
    internal_ambiguous: Literal["exact", "trust"] = Field(
        "exact", description="a ray that also confidently hits a box it starts inside, other "
                             "than the chosen one: forward exactly, or trust the prediction")

    @field_validator("accuracy", mode="before")
    @classmethod
    def _parse_accuracy(cls, v):
        return parse_accuracy(v)

    @model_validator(mode="before")
    @classmethod
    def _bands_or_accuracy(cls, data):
        """Hand-set bands without an accuracy mean the bands are wanted as given."""
        if isinstance(data, dict) and "accuracy" not in data and (
                data.get("band") is not None or data.get("shadow_band") is not None):
            data = {**data, "accuracy": None}
        return data


# Samples per pixel of one pass (a tile's sample chunk). At most one pass per tile is live,
# so on an image of few tiles the window is the tile count, and each pass's last bounces are
# a tail of small steps before the tile's next pass may start. 16 (was 4) puts 4x the rays
# in each live pass: at 640x360, 16 spp (60 tiles), K = 8 in one process, exact CPU
# 1.26-1.64x the one-shard CPU instead of 1.38-2.00x and proxy 1.53-1.64x instead of
# 1.80-1.99x, with about 4x fewer steps (bench/README.md, "Bigger passes"). A progressive
# preview refines every 16 samples; pass --spp-per-pass 1 for a first look sooner.
SPP_PER_PASS = 16


class RenderSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    width: int = Field(256, ge=1, le=16384, description="image width, pixels")
    height: int = Field(256, ge=1, le=16384, description="image height, pixels")
    spp: int = Field(16, ge=1, le=1 << 16, description="samples per pixel")
    bounces: int = Field(5, ge=0, le=64, description="maximum path depth B")
    shadow_rays: int = Field(4, ge=0, le=64, description="next-event shadow rays S per hit")
    seed: int = Field(0, ge=0, lt=1 << 63)
    russian_roulette: bool = Field(False, description="terminate low-throughput paths from depth 3")
    mode: Mode = "exact"
    shards: int = Field(0, ge=0, le=64, description="K shard actors; 0 = single-process reference")
    tile_size: int = Field(64, ge=8, le=4096, description="tile edge, pixels")
    spp_per_pass: int = Field(SPP_PER_PASS, ge=1, le=1 << 16,
                              description="samples per pixel in one pass")
    byte_slack: float = Field(
        BYTE_SLACK, ge=1.0, le=16.0,
        description="a shard may hold this times the geometry bytes of the largest shard "
                    "under a bytes-only placement, so that placement can balance ray work; "
                    "wider balances better where meshes are few and alike in size (K >= 8), "
                    "at more memory per shard")
    proxy: ProxySettings = Field(default_factory=ProxySettings)

    @model_validator(mode="after")
    def _check(self):
        if self.mode != "exact" and self.shards == 0:
            raise ValueError(f"mode {self.mode!r} needs shards >= 1 (got shards=0)")
        if self.spp_per_pass > self.spp:  # the same passes; a job then says what it renders
            object.__setattr__(self, "spp_per_pass", self.spp)
        return self
