"""Errors the job API, the scheduler and the scene store raise; REST and gRPC map them to
status codes."""


class ServiceError(Exception):
    """Base class; the message is meant for the API client."""


class NotFound(ServiceError):
    """Unknown job or scene id (HTTP 404, gRPC NOT_FOUND)."""


class Conflict(ServiceError):
    """The request does not fit the job's state, e.g. cancelling a finished job (409,
    FAILED_PRECONDITION)."""


class BadUpload(ServiceError):
    """A malformed or unsafe upload: unknown format, zip-slip path, no scene inside (400)."""


class TooLarge(ServiceError):
    """An upload or its extracted content over the configured limit (413)."""


class InvalidScene(ServiceError):
    """The upload is well-formed but the scene does not load: carries SceneError's message
    (422, INVALID_ARGUMENT)."""


class InvalidJob(ServiceError):
    """Job settings the service refuses although RenderSettings accepts them, or an unknown
    scene (422 naming `field`, INVALID_ARGUMENT)."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field


class UnknownScene(InvalidJob):
    """A job names a scene that is neither stored nor a demo."""

    def __init__(self, message: str):
        super().__init__("scene", message)


class TooManyWatchers(ServiceError):
    """More event streams open than NPRT_MAX_WATCHERS (503, RESOURCE_EXHAUSTED)."""


class QueueFull(ServiceError):
    """NPRT_MAX_QUEUED_JOBS jobs are queued: come back after Retry-After (429,
    RESOURCE_EXHAUSTED)."""


class StoreBusy(ServiceError):
    """The job store stayed locked by another process's write (503 with Retry-After,
    UNAVAILABLE)."""


def redact_paths(message: str, roots: list[str]) -> str:
    """The message without the server's directories: a client knows its own file names,
    and absolute server paths tell an attacker the layout."""
    for root in sorted({r.rstrip("/") for r in roots if r and r != "/"}, key=len,
                       reverse=True):
        message = message.replace(root + "/", "").replace(root, "<server>")
    return message
