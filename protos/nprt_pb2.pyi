from google.protobuf import struct_pb2 as _struct_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class JobState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    JOB_STATE_UNSPECIFIED: _ClassVar[JobState]
    JOB_STATE_QUEUED: _ClassVar[JobState]
    JOB_STATE_PREPARING: _ClassVar[JobState]
    JOB_STATE_RUNNING: _ClassVar[JobState]
    JOB_STATE_SUCCEEDED: _ClassVar[JobState]
    JOB_STATE_FAILED: _ClassVar[JobState]
    JOB_STATE_CANCELED: _ClassVar[JobState]

class TileFormat(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    TILE_FORMAT_NONE: _ClassVar[TileFormat]
    TILE_FORMAT_PNG: _ClassVar[TileFormat]
    TILE_FORMAT_RGB_F32: _ClassVar[TileFormat]

class ImageFormat(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    IMAGE_FORMAT_PNG: _ClassVar[ImageFormat]
    IMAGE_FORMAT_EXR: _ClassVar[ImageFormat]
JOB_STATE_UNSPECIFIED: JobState
JOB_STATE_QUEUED: JobState
JOB_STATE_PREPARING: JobState
JOB_STATE_RUNNING: JobState
JOB_STATE_SUCCEEDED: JobState
JOB_STATE_FAILED: JobState
JOB_STATE_CANCELED: JobState
TILE_FORMAT_NONE: TileFormat
TILE_FORMAT_PNG: TileFormat
TILE_FORMAT_RGB_F32: TileFormat
IMAGE_FORMAT_PNG: ImageFormat
IMAGE_FORMAT_EXR: ImageFormat

class ProxySettings(_message.Message):
    __slots__ = ("threshold", "band", "accuracy_target")
    THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    BAND_FIELD_NUMBER: _ClassVar[int]
    ACCURACY_TARGET_FIELD_NUMBER: _ClassVar[int]
    threshold: float
    band: float
    accuracy_target: float
    def __init__(self, threshold: _Optional[float] = ..., band: _Optional[float] = ..., accuracy_target: _Optional[float] = ...) -> None: ...

class RenderSettings(_message.Message):
    __slots__ = ("width", "height", "spp", "bounces", "shadow_rays", "seed", "russian_roulette", "mode", "shards", "tile_size", "spp_per_pass", "proxy")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    SPP_FIELD_NUMBER: _ClassVar[int]
    BOUNCES_FIELD_NUMBER: _ClassVar[int]
    SHADOW_RAYS_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    RUSSIAN_ROULETTE_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    SHARDS_FIELD_NUMBER: _ClassVar[int]
    TILE_SIZE_FIELD_NUMBER: _ClassVar[int]
    SPP_PER_PASS_FIELD_NUMBER: _ClassVar[int]
    PROXY_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    spp: int
    bounces: int
    shadow_rays: int
    seed: int
    russian_roulette: bool
    mode: str
    shards: int
    tile_size: int
    spp_per_pass: int
    proxy: ProxySettings
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., spp: _Optional[int] = ..., bounces: _Optional[int] = ..., shadow_rays: _Optional[int] = ..., seed: _Optional[int] = ..., russian_roulette: _Optional[bool] = ..., mode: _Optional[str] = ..., shards: _Optional[int] = ..., tile_size: _Optional[int] = ..., spp_per_pass: _Optional[int] = ..., proxy: _Optional[_Union[ProxySettings, _Mapping]] = ...) -> None: ...

class Job(_message.Message):
    __slots__ = ("id", "scene", "state", "settings", "passes_done", "passes_total", "progress", "error", "created_at_unix_s", "started_at_unix_s", "finished_at_unix_s", "stats")
    ID_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    SETTINGS_FIELD_NUMBER: _ClassVar[int]
    PASSES_DONE_FIELD_NUMBER: _ClassVar[int]
    PASSES_TOTAL_FIELD_NUMBER: _ClassVar[int]
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    CREATED_AT_UNIX_S_FIELD_NUMBER: _ClassVar[int]
    STARTED_AT_UNIX_S_FIELD_NUMBER: _ClassVar[int]
    FINISHED_AT_UNIX_S_FIELD_NUMBER: _ClassVar[int]
    STATS_FIELD_NUMBER: _ClassVar[int]
    id: str
    scene: str
    state: JobState
    settings: RenderSettings
    passes_done: int
    passes_total: int
    progress: float
    error: str
    created_at_unix_s: float
    started_at_unix_s: float
    finished_at_unix_s: float
    stats: _struct_pb2.Struct
    def __init__(self, id: _Optional[str] = ..., scene: _Optional[str] = ..., state: _Optional[_Union[JobState, str]] = ..., settings: _Optional[_Union[RenderSettings, _Mapping]] = ..., passes_done: _Optional[int] = ..., passes_total: _Optional[int] = ..., progress: _Optional[float] = ..., error: _Optional[str] = ..., created_at_unix_s: _Optional[float] = ..., started_at_unix_s: _Optional[float] = ..., finished_at_unix_s: _Optional[float] = ..., stats: _Optional[_Union[_struct_pb2.Struct, _Mapping]] = ...) -> None: ...

class SubmitJobRequest(_message.Message):
    __slots__ = ("scene", "settings")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    SETTINGS_FIELD_NUMBER: _ClassVar[int]
    scene: str
    settings: RenderSettings
    def __init__(self, scene: _Optional[str] = ..., settings: _Optional[_Union[RenderSettings, _Mapping]] = ...) -> None: ...

class GetJobRequest(_message.Message):
    __slots__ = ("job_id",)
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    def __init__(self, job_id: _Optional[str] = ...) -> None: ...

class ListJobsRequest(_message.Message):
    __slots__ = ("offset", "limit")
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    LIMIT_FIELD_NUMBER: _ClassVar[int]
    offset: int
    limit: int
    def __init__(self, offset: _Optional[int] = ..., limit: _Optional[int] = ...) -> None: ...

class ListJobsResponse(_message.Message):
    __slots__ = ("jobs", "total")
    JOBS_FIELD_NUMBER: _ClassVar[int]
    TOTAL_FIELD_NUMBER: _ClassVar[int]
    jobs: _containers.RepeatedCompositeFieldContainer[Job]
    total: int
    def __init__(self, jobs: _Optional[_Iterable[_Union[Job, _Mapping]]] = ..., total: _Optional[int] = ...) -> None: ...

class WatchJobRequest(_message.Message):
    __slots__ = ("job_id", "tile_format")
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    TILE_FORMAT_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    tile_format: TileFormat
    def __init__(self, job_id: _Optional[str] = ..., tile_format: _Optional[_Union[TileFormat, str]] = ...) -> None: ...

class Rect(_message.Message):
    __slots__ = ("x0", "y0", "x1", "y1")
    X0_FIELD_NUMBER: _ClassVar[int]
    Y0_FIELD_NUMBER: _ClassVar[int]
    X1_FIELD_NUMBER: _ClassVar[int]
    Y1_FIELD_NUMBER: _ClassVar[int]
    x0: int
    y0: int
    x1: int
    y1: int
    def __init__(self, x0: _Optional[int] = ..., y0: _Optional[int] = ..., x1: _Optional[int] = ..., y1: _Optional[int] = ...) -> None: ...

class Tile(_message.Message):
    __slots__ = ("pass_index", "passes_total", "rect", "sample0", "sample1", "progress", "format", "pixels")
    PASS_INDEX_FIELD_NUMBER: _ClassVar[int]
    PASSES_TOTAL_FIELD_NUMBER: _ClassVar[int]
    RECT_FIELD_NUMBER: _ClassVar[int]
    SAMPLE0_FIELD_NUMBER: _ClassVar[int]
    SAMPLE1_FIELD_NUMBER: _ClassVar[int]
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    PIXELS_FIELD_NUMBER: _ClassVar[int]
    pass_index: int
    passes_total: int
    rect: Rect
    sample0: int
    sample1: int
    progress: float
    format: TileFormat
    pixels: bytes
    def __init__(self, pass_index: _Optional[int] = ..., passes_total: _Optional[int] = ..., rect: _Optional[_Union[Rect, _Mapping]] = ..., sample0: _Optional[int] = ..., sample1: _Optional[int] = ..., progress: _Optional[float] = ..., format: _Optional[_Union[TileFormat, str]] = ..., pixels: _Optional[bytes] = ...) -> None: ...

class JobEvent(_message.Message):
    __slots__ = ("job", "tile")
    JOB_FIELD_NUMBER: _ClassVar[int]
    TILE_FIELD_NUMBER: _ClassVar[int]
    job: Job
    tile: Tile
    def __init__(self, job: _Optional[_Union[Job, _Mapping]] = ..., tile: _Optional[_Union[Tile, _Mapping]] = ...) -> None: ...

class CancelJobRequest(_message.Message):
    __slots__ = ("job_id",)
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    def __init__(self, job_id: _Optional[str] = ...) -> None: ...

class GetImageRequest(_message.Message):
    __slots__ = ("job_id", "format")
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    format: ImageFormat
    def __init__(self, job_id: _Optional[str] = ..., format: _Optional[_Union[ImageFormat, str]] = ...) -> None: ...

class Image(_message.Message):
    __slots__ = ("job_id", "format", "data", "width", "height", "partial")
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    PARTIAL_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    format: ImageFormat
    data: bytes
    width: int
    height: int
    partial: bool
    def __init__(self, job_id: _Optional[str] = ..., format: _Optional[_Union[ImageFormat, str]] = ..., data: _Optional[bytes] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., partial: _Optional[bool] = ...) -> None: ...
