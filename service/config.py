"""Service settings: one pydantic BaseSettings class, read from NPRT_* environment variables."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


def _in_data_dir(name: str, doc: str | None = None) -> property:
    """A read-only property: the path `name` inside the settings' data_dir."""
    return property(lambda self: self.data_dir / name, doc=doc)


class ServiceSettings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="NPRT_", extra="ignore")

    data_dir: Path = Field(Path("nprt-data"), description="jobs, scenes, proxies and the SQLite db")
    ray_address: str | None = Field(None, description="Ray cluster address; unset = local Ray")
    max_concurrent_jobs: int = Field(1, ge=1, le=64, description="jobs rendering at once")
    max_sharded_jobs: int = Field(1, ge=1, le=64,
                                  description="sharded (Ray) jobs rendering at once; each "
                                              "Coordinator sizes its actors to the whole cluster")
    max_upload_bytes: int = Field(256 << 20, ge=1, description="largest scene upload, bytes")
    max_extracted_bytes: int = Field(1 << 30, ge=1,
                                     description="largest unpacked zip upload, bytes")
    max_image_pixels: int = Field(4096 * 4096, ge=1,
                                  description="largest width * height of a job; the film "
                                              "takes 32 bytes per pixel")
    max_job_samples: int = Field(1 << 32, ge=1,
                                 description="largest width * height * spp of a job, samples; "
                                             "refused at submission with 422")
    api_token: str | None = Field(None, min_length=1,
                                  description="Bearer token for writing endpoints; unset = open")
    grpc_max_message_bytes: int = Field(64 << 20, ge=1 << 20,
                                        description="gRPC message limit, bytes (tiles, images)")
    scene_cache_size: int = Field(8, ge=0, description="loaded scenes kept in memory")
    # Unset: PoolRegistry's own defaults (nprt.workers.runtime.pool), the one definition.
    pool_max_bytes: int | None = Field(None, ge=0,
                                       description="geometry bytes that idle warm shard pools "
                                                   "may hold; least recently used pools go "
                                                   "first (unset: the pool registry's default)")
    pool_max_count: int | None = Field(None, ge=1, le=64,
                                       description="warm shard pools kept at most (unset: the "
                                                   "pool registry's default)")
    checkpoint_interval_s: float = Field(
        5.0, ge=0.0, le=3600.0,
        description="seconds between film checkpoints of a running job (0 = every pass); a "
                    "restart loses at most this much work")
    max_watchers: int = Field(1_000, ge=1, description="SSE and gRPC event streams open at "
                                                       "once; more get 503 / RESOURCE_EXHAUSTED")
    watcher_tile_bytes: int = Field(8 << 20, ge=0,
                                    description="tile pixels a slow watcher may have pending, "
                                                "bytes; older tiles beyond it are dropped")
    max_job_retries: int = Field(2, ge=0, le=100,
                                 description="times a job that lost its Ray shards (a node "
                                             "died) is re-queued from its checkpoint")
    max_queued_jobs: int = Field(1_000, ge=1,
                                 description="jobs waiting in the queue at most; past it a "
                                             "submission gets 429 with Retry-After (the "
                                             "default admits a burst of 500)")
    retry_after_s: int = Field(2, ge=1, le=3600,
                               description="Retry-After of a 429 or 503 answer, seconds")
    api_workers: int | None = Field(
        None, ge=1, le=64, description="HTTP API worker processes of `nprt serve` "
                                       "(--workers), sharing the port and the store; unset: "
                                       "2 on a host with 2 or more cores, else 1")
    scheduler_cpu: Literal["idle", "batch", "off"] = Field(
        "idle", description="CPU policy of the scheduler and everything it starts (Ray, "
                            "renders): idle (SCHED_IDLE: an API worker of the same session "
                            "that wakes preempts a render at once), batch (SCHED_BATCH), "
                            "off (as started); service/priority.py")
    scheduler_nice: int = Field(10, ge=0, le=19,
                                description="niceness of the scheduler and the Ray "
                                            "processes it starts, unless scheduler_cpu is off")
    scheduler_own_session: bool = Field(
        False, description="run the scheduler in a session (an autogroup) of its own: the "
                            "kernel then shares the CPU between it and the API's session "
                            "before the CPU policy counts, so renders take up to half of "
                            "it from the API")
    scheduler_session_nice: int = Field(
        0, ge=0, le=19,
        description="nice of the scheduler session's autogroup (Linux autogroup scheduling "
                    "shares the CPU between sessions first): 10 holds renders back against "
                    "every other session too, but on a host busy with other sessions it "
                    "slows Ray's start to minutes")
    ray_start_attempts: int = Field(3, ge=1, le=20,
                                    description="tries at starting or joining Ray per job")

    db_path = _in_data_dir("jobs.sqlite3")
    jobs_dir = _in_data_dir("jobs")
    scenes_dir = _in_data_dir("scenes")
    proxies_dir = _in_data_dir("proxies")
    tmp_dir = _in_data_dir("tmp", "Uploads are spooled here, on the same filesystem as the "
                                  "store, for os.replace.")
