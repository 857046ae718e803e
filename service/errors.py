"""Errors the job API, the scheduler and the scene store raise, each with the status REST
and gRPC answer it with (one table for both front ends)."""


class ServiceError(Exception):
    """Base class; the message is meant for the API client."""

    http_status = 400
    grpc_code = "INVALID_ARGUMENT"  # a grpc.StatusCode name
    retry_after = False  # answered with Retry-After: the same request may succeed later


class NotFound(ServiceError):
    """Unknown job or scene id."""

    http_status, grpc_code = 404, "NOT_FOUND"


class Conflict(ServiceError):
    """The request does not fit the job's state, e.g. cancelling a finished job."""

    http_status, grpc_code = 409, "FAILED_PRECONDITION"


class BadUpload(ServiceError):
    """A malformed or unsafe upload: unknown format, zip-slip path, no scene inside."""


class TooLarge(ServiceError):
    """An upload or its extracted content over the configured limit."""

    http_status = 413


class InvalidScene(ServiceError):
    """The upload is well-formed but the scene does not load: carries SceneError's
    message."""

    http_status = 422


class InvalidJob(ServiceError):
    """Job settings the service refuses although RenderSettings accepts them, or an unknown
    scene (naming `field`)."""

    http_status = 422

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field


class UnknownScene(InvalidJob):
    """A job names a scene that is neither stored nor a demo."""

    def __init__(self, message: str):
        super().__init__("scene", message)


class TooManyWatchers(ServiceError):
    """More event streams open than NPRT_MAX_WATCHERS."""

    http_status, grpc_code = 503, "RESOURCE_EXHAUSTED"


class QueueFull(ServiceError):
    """NPRT_MAX_QUEUED_JOBS jobs are queued: come back after Retry-After."""

    http_status, grpc_code, retry_after = 429, "RESOURCE_EXHAUSTED", True


class StoreBusy(ServiceError):
    """The job store stayed locked by another process's write."""

    http_status, grpc_code, retry_after = 503, "UNAVAILABLE", True


def redact_paths(message: str, roots: list[str]) -> str:
    """The message without the server's directories: a client knows its own file names,
    and absolute server paths tell an attacker the layout."""
    for root in sorted({r.rstrip("/") for r in roots if r and r != "/"}, key=len,
                       reverse=True):
        message = message.replace(root + "/", "").replace(root, "<server>")
    return message
