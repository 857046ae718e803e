"""The optional API token: writing endpoints need it (REST 401, gRPC UNAUTHENTICATED)."""

from __future__ import annotations

import grpc
import httpx
import pytest

from nprt.protos import nprt_pb2 as pb
from nprt.protos import nprt_pb2_grpc
from tests.service.helpers import TINY, LiveServer, problem_detail, settings_for

TOKEN = "s3cret-token"


@pytest.fixture(scope="module")
def guarded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("auth")
    with LiveServer(settings_for(tmp, api_token=TOKEN), grpc=True) as server:
        yield server


@pytest.fixture
def anon(guarded):
    with httpx.Client(base_url=guarded.url, timeout=30.0) as c:
        yield c


@pytest.mark.parametrize("headers,detail", [
    ({}, "missing bearer token"),
    ({"Authorization": "Bearer wrong"}, "wrong bearer token"),
    ({"Authorization": f"Basic {TOKEN}"}, "missing bearer token")])
def test_writing_endpoints_need_the_token(anon, headers, detail):
    job = anon.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}, headers=headers)
    assert job.status_code == 401 and problem_detail(job) == detail
    assert job.headers["www-authenticate"] == "Bearer"
    scene = anon.post("/v1/scenes", content=b"glTF....", headers=headers)
    assert scene.status_code == 401 and problem_detail(scene) == detail
    cancel = anon.post("/v1/jobs/abc/cancel", headers=headers)
    assert cancel.status_code == 401 and problem_detail(cancel) == detail
    delete = anon.delete("/v1/jobs/abc", headers=headers)
    assert delete.status_code == 401 and problem_detail(delete) == detail


def test_right_token_writes_and_reads_stay_open(anon):
    r = anon.post("/v1/jobs", json={"scene": "forest:tiny", **TINY},
                  headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 202, r.text
    got = anon.get(f"/v1/jobs/{r.json()['id']}")
    assert got.status_code == 200 and got.json()["id"] == r.json()["id"]
    assert anon.get("/v1/jobs").status_code == 200


def test_grpc_writes_need_the_token_in_metadata(guarded):
    with grpc.insecure_channel(guarded.grpc_target) as ch:
        stub = nprt_pb2_grpc.RenderServiceStub(ch)
        request = pb.SubmitJobRequest(scene="forest:tiny", settings=pb.RenderSettings(**TINY))
        for metadata in ((), (("authorization", "Bearer wrong"),)):
            with pytest.raises(grpc.RpcError) as e:
                stub.SubmitJob(request, metadata=metadata, timeout=10)
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
            assert e.value.details() == "missing or wrong bearer token"
        job = stub.SubmitJob(request, metadata=(("authorization", f"Bearer {TOKEN}"),))
        assert stub.GetJob(pb.GetJobRequest(job_id=job.id)).id == job.id  # reads stay open


@pytest.mark.parametrize("scheme", ["bearer", "BEARER", "Bearer"])
def test_bearer_scheme_is_case_insensitive_on_rest_and_grpc(anon, guarded, scheme):
    r = anon.post("/v1/jobs", json={"scene": "forest:tiny", **TINY},
                  headers={"Authorization": f"{scheme} {TOKEN}"})
    assert r.status_code == 202, r.text
    with grpc.insecure_channel(guarded.grpc_target) as ch:
        stub = nprt_pb2_grpc.RenderServiceStub(ch)
        job = stub.CancelJob(pb.CancelJobRequest(job_id=r.json()["id"]),
                             metadata=(("authorization", f"{scheme} {TOKEN}"),), timeout=10)
        assert job.id == r.json()["id"] and job.cancel_requested


@pytest.mark.parametrize("body", [b"{not json", b"\xff\xfe", b'{"scene": ' + b"[" * 10_000])
def test_token_is_checked_before_the_body_is_parsed(anon, body):
    r = anon.post("/v1/jobs", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 401 and problem_detail(r) == "missing bearer token"
    r = anon.post("/v1/jobs", content=body, headers={"Content-Type": "application/json",
                                                     "Authorization": "Bearer wrong"})
    assert r.status_code == 401 and problem_detail(r) == "wrong bearer token"
    ok = anon.post("/v1/jobs", content=body, headers={"Content-Type": "application/json",
                                                      "Authorization": f"Bearer {TOKEN}"})
    # With the token the body is read: 422 for bad JSON, 400 for JSON nested too deeply.
    assert ok.status_code in (400, 422) and problem_detail(ok)
