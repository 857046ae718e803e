"""Every REST error is RFC 9457 problem details, whatever raised it, and the OpenAPI schema
says so for every error status code."""

from __future__ import annotations

from nprt.service.problems import PROBLEM_MEDIA_TYPE
from tests.service.helpers import problem_detail


def _problem(r, status: int) -> dict:
    assert r.status_code == status, r.text
    problem_detail(r)  # content type, status, title, type
    return r.json()


def test_unknown_job_is_a_not_found_problem(client):
    body = _problem(client.get("/v1/jobs/0123abcd"), 404)
    assert body == {"type": "urn:nprt:problem:not-found", "title": "Not found", "status": 404,
                    "detail": "no job with id '0123abcd'", "instance": "/v1/jobs/0123abcd"}


def test_invalid_field_names_it_in_detail_and_errors(client):
    body = _problem(client.post("/v1/jobs", json={"scene": "forest:tiny", "spp": 0}), 422)
    assert body["type"] == "urn:nprt:problem:invalid-request"
    assert body["detail"].startswith("body.spp: Input should be greater than or equal to 1")
    assert [e["loc"] for e in body["errors"]] == [["body", "spp"]]


def test_service_limit_is_the_same_shape_as_a_validation_error(client):
    body = _problem(client.post("/v1/jobs", json={"scene": "moon:tiny"}), 422)
    assert body["type"] == "urn:nprt:problem:invalid-request"
    assert body["errors"][0]["loc"] == ["body", "scene"]
    assert body["detail"].startswith("body.scene: unknown scene 'moon:tiny'")


def test_unknown_route_and_wrong_method_are_plain_http_problems(client):
    body = _problem(client.get("/v1/nothing-here"), 404)
    assert (body["type"], body["title"], body["instance"]) == ("about:blank", "Not Found",
                                                               "/v1/nothing-here")
    body = _problem(client.put("/v1/jobs"), 405)
    assert body["title"] == "Method Not Allowed"


def test_openapi_documents_every_error_as_a_problem(client):
    schema = client.get("/openapi.json").json()
    errors = [(path, method, code, response)
              for path, ops in schema["paths"].items() for method, op in ops.items()
              for code, response in op["responses"].items() if code[0] in "45"]
    assert len(errors) >= 20
    for path, method, code, response in errors:
        assert response["content"] == {PROBLEM_MEDIA_TYPE: {
            "schema": {"$ref": "#/components/schemas/Problem"}}}, (path, method, code)
    components = schema["components"]["schemas"]
    assert {"type", "title", "status", "detail"} <= set(components["Problem"]["properties"])
    assert "HTTPValidationError" not in components
