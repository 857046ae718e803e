"""Every REST error answer as RFC 9457 problem details (`application/problem+json`): one
shape whatever raised it, declared in the OpenAPI schema for every error status code."""

from __future__ import annotations

import re
from http import HTTPStatus

from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

PROBLEM_MEDIA_TYPE = "application/problem+json"
# nprt's own problem types are URNs: stable names a client can branch on, not pages to fetch.
TYPE_PREFIX = "urn:nprt:problem:"


class Problem(BaseModel):
    """RFC 9457 problem details; `errors` is nprt's extension for invalid fields."""

    type: str = Field("about:blank", description="URI naming the problem type: "
                      f"`{TYPE_PREFIX}<name>` for nprt's own (not-found, conflict, "
                      "bad-upload, too-large, invalid-scene, invalid-job, unknown-scene, "
                      "too-many-watchers, invalid-request), `about:blank` for plain HTTP "
                      "status semantics")
    title: str = Field(description="short summary of the problem type")
    status: int = Field(ge=400, le=599, description="the HTTP status code, repeated")
    detail: str = Field(description="what went wrong with this request, for a person")
    instance: str | None = Field(None, description="the request path")
    errors: list[dict] | None = Field(None, description="422 only: each invalid field, as "
                                      "{loc, msg, type, input}")


def type_name(cls: type) -> str:
    """`InvalidScene` -> `urn:nprt:problem:invalid-scene`."""
    return TYPE_PREFIX + re.sub(r"(?<!^)(?=[A-Z])", "-", cls.__name__).lower()


def problem_response(status: int, detail: str, *, type_: str = "about:blank",
                     title: str | None = None, instance: str | None = None,
                     errors: list[dict] | None = None,
                     headers: dict[str, str] | None = None) -> JSONResponse:
    """A problem+json answer; title defaults to the status phrase (RFC 9457 section 4.2.1)."""
    body = Problem(type=type_, title=title or HTTPStatus(status).phrase, status=status,
                   detail=detail, instance=instance, errors=errors)
    return JSONResponse(body.model_dump(exclude_none=True), status_code=status,
                        headers=headers, media_type=PROBLEM_MEDIA_TYPE)


def describe_fields(errors: list[dict]) -> str:
    """FastAPI validation errors in one line: `body.spp: Input should be > 0 (got 0)`."""
    return "; ".join(f"{'.'.join(map(str, e.get('loc', ())))}: {e.get('msg')}"
                     + (f" (got {e['input']!r})" if "input" in e else "") for e in errors)


def document_problems(schema: dict) -> dict:
    """Point every error response of an OpenAPI schema at Problem as problem+json,
    in place of the application/json FastAPI writes (and its HTTPValidationError)."""
    ref = {"$ref": "#/components/schemas/Problem"}
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            for code, response in operation.get("responses", {}).items():
                if code[0] in "45":
                    response["content"] = {PROBLEM_MEDIA_TYPE: {"schema": ref}}
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components["Problem"] = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
    for unused in ("HTTPValidationError", "ValidationError"):
        components.pop(unused, None)
    return schema
