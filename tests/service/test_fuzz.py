"""Fuzzing, bounded in cases and time: the REST API from its own OpenAPI schema
(schemathesis, positive and negative data) and the upload endpoint (garbage, truncated and
mutated zips, zip bombs, slips, symlinks, huge and deeply nested JSON). Over 1,000 cases:
no 5xx, no hang (every request has a timeout), every status code declared in the schema,
and no error body shows a server path."""

from __future__ import annotations

import io
import json
import stat
import zipfile
from collections import Counter

import httpx
import pytest
import trimesh

schemathesis = pytest.importorskip("schemathesis")
hypothesis = pytest.importorskip("hypothesis")

from hypothesis import HealthCheck, Phase, given  # noqa: E402
from hypothesis import settings as hsettings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from schemathesis import GenerationMode  # noqa: E402
from schemathesis.checks import (  # noqa: E402
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

from nprt.service.problems import PROBLEM_MEDIA_TYPE, Problem  # noqa: E402
from tests.service.helpers import LiveServer, settings_for  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

REST_EXAMPLES = 60  # per operation and generation mode
UPLOAD_EXAMPLES = 500
REQUEST_TIMEOUT_S = 30.0  # a request that takes longer counts as a hang
UPLOAD_STATUSES = {200, 201, 400, 413, 422}
MAX_UPLOAD_BYTES = 4 << 20
MAX_EXTRACTED_BYTES = 1 << 20
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_schema_conformance]


def _fuzz_settings(**extra):
    return hsettings(deadline=None, database=None, derandomize=True,
                     suppress_health_check=list(HealthCheck),
                     phases=[Phase.explicit, Phase.generate], **extra)


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory):
    """A server that stores jobs but never renders them (the fuzzer may submit hundreds),
    with small upload limits so a bomb is quick to refuse."""
    root = tmp_path_factory.mktemp("fuzz")
    settings = settings_for(root, max_upload_bytes=MAX_UPLOAD_BYTES,
                            max_extracted_bytes=MAX_EXTRACTED_BYTES)
    with LiveServer(settings, scheduler=False) as server:
        yield server


def _server_paths(server) -> list[str]:
    data = server.settings.data_dir
    return sorted({str(data.absolute()), str(data.resolve())})


def _check_no_paths(server, text: str) -> None:
    for path in _server_paths(server):
        assert path not in text, f"a response shows the server path {path}: {text[:300]}"


def _fuzz_operation(server, op, mode, job_id: str, statuses: Counter,
                    failures: list[str]) -> None:
    """REST_EXAMPLES cases of one operation; half of them aimed at a real scene and job."""
    @_fuzz_settings(max_examples=REST_EXAMPLES)
    @given(case=op.as_strategy(mode), real=st.booleans())
    def run(case, real):
        if real and isinstance(case.body, dict):
            case.body["scene"] = "forest:tiny"  # get past the scene check
        if real and "job_id" in (case.path_parameters or {}):
            case.path_parameters["job_id"] = job_id
        try:
            response = case.call(base_url=server.url, timeout=REQUEST_TIMEOUT_S)
        except (ValueError, UnicodeError) as e:
            # The HTTP client refused to send it (e.g. CR in a header): no request was made.
            statuses[(op.label, f"not sent: {type(e).__name__}")] += 1
            return
        statuses[(op.label, response.status_code)] += 1
        try:
            case.validate_response(response, checks=CHECKS)
            _check_no_paths(server, response.text)
        except Exception as e:  # AssertionError or schemathesis' failures: report them all
            failures.append(f"{op.label} [{mode.value}] -> {response.status_code}: "
                            f"{str(e)[:400]}\n  {case.as_curl_command()[:300]}")

    run()


def test_rest_api_fuzzed_from_its_openapi_schema(fuzzed):
    with httpx.Client(base_url=fuzzed.url, timeout=REQUEST_TIMEOUT_S) as client:
        # A finished job, so fuzzed paths also reach an existing one (cancel -> 409, events
        # -> a stream that ends at once).
        done = client.post("/v1/jobs", json={"scene": "forest:tiny", "width": 8,
                                             "height": 8}).json()["id"]
        assert client.post(f"/v1/jobs/{done}/cancel").json()["state"] == "canceled"
    schema = schemathesis.openapi.from_url(f"{fuzzed.url}/openapi.json")
    statuses: Counter = Counter()
    failures: list[str] = []
    for result in schema.get_all_operations():
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):
            try:
                _fuzz_operation(fuzzed, result.ok(), mode, done, statuses, failures)
            except hypothesis.errors.Unsatisfiable:  # no negative data for a bare GET
                pass
    sent = sum(n for (_, code), n in statuses.items() if isinstance(code, int))
    summary = "\n".join(f"{k}: {v}" for k, v in sorted(statuses.items(), key=str))
    assert not failures, "\n".join(failures[:20]) + f"\n{len(failures)} failures\n{summary}"
    assert sent >= 600, summary
    assert not any(isinstance(code, int) and code >= 500 for _, code in statuses)
    assert statuses[("POST /v1/jobs", 202)] > 0, summary  # the fuzzer got past validation
    fuzzed.rest_cases = sent


# ---------------------------------------------------------------- uploads

def _zip(members: list[tuple[zipfile.ZipInfo | str, bytes]],
         method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as zf:
        for info, data in members:
            zf.writestr(info, data)
    return buf.getvalue()


def _scene_doc(mesh_path: str = "meshes/ball.ply") -> dict:
    return {"name": "fuzz", "meshes": [{"name": "ball", "path": mesh_path}],
            "instances": [{"mesh": "ball", "translate": [0, 0, 0]}],
            "environment": {"kind": "constant", "radiance": [1, 1, 1]}}


PLY = trimesh.creation.icosphere(subdivisions=1).export(file_type="ply")
VALID_ZIP = _zip([("scene.json", json.dumps(_scene_doc()).encode()), ("meshes/ball.ply", PLY)])
BOMB = _zip([("scene.json", json.dumps(_scene_doc()).encode()),
             ("meshes/ball.ply", b"\0" * (64 << 20))])  # 64 MiB of zeros in ~64 KiB
SLIPS = ["../evil.ply", "/etc/evil.ply", "a/../../evil.ply", "C:/evil.ply", "a\\..\\evil",
         "..", "/", "./", ".", "a/./../../b", "p" * 300, "d/" * 600 + "m"]


def _symlink(name: str, target: str) -> tuple[zipfile.ZipInfo, bytes]:
    info = zipfile.ZipInfo(name)
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info, target.encode()


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=10), inner,
                                                                max_size=5),
    max_leaves=30)


@st.composite
def uploads(draw) -> tuple[str, bytes]:
    kind = draw(st.sampled_from(["garbage", "truncated", "mutated", "bomb", "slip", "symlink",
                                 "mesh path", "json", "json in zip", "nested", "huge json",
                                 "zip of many", "glb-ish"]))
    if kind == "garbage":
        return kind, draw(st.binary(min_size=1, max_size=2048))
    if kind == "truncated":
        return kind, VALID_ZIP[:draw(st.integers(1, len(VALID_ZIP) - 1))]
    if kind == "mutated":
        data = bytearray(VALID_ZIP)
        for at, value in draw(st.lists(st.tuples(st.integers(0, len(data) - 1),
                                                 st.integers(0, 255)), min_size=1, max_size=8)):
            data[at] = value
        return kind, bytes(data)
    if kind == "bomb":
        return kind, BOMB
    if kind == "slip":
        # (zipfile itself cuts a name at a NUL byte, so none are drawn)
        name = draw(st.sampled_from(SLIPS) | st.text(
            st.characters(blacklist_characters="\x00"), min_size=1, max_size=40))
        return kind, _zip([("scene.json", json.dumps(_scene_doc()).encode()), (name, PLY)])
    if kind == "symlink":
        target = draw(st.sampled_from(["/etc/passwd", "../../../etc/passwd", "ball.ply"]))
        return kind, _zip([("scene.json", json.dumps(_scene_doc()).encode()),
                           _symlink("meshes/ball.ply", target)])
    if kind == "mesh path":  # the scene names a file elsewhere on the server
        path = draw(st.sampled_from(["/etc/passwd", "../../../../etc/passwd",
                                     "meshes/../../x.ply", "/proc/self/environ"]))
        return kind, _zip([("scene.json", json.dumps(_scene_doc(path)).encode()),
                           ("meshes/ball.ply", PLY)])
    if kind == "json":
        return kind, b"{" + json.dumps(draw(json_values)).encode()[1:] if draw(st.booleans()) \
            else json.dumps({"meshes": draw(json_values)}).encode()
    if kind == "json in zip":
        doc = draw(st.dictionaries(st.sampled_from(["name", "meshes", "instances",
                                                    "environment", "camera"]), json_values))
        return kind, _zip([("scene.json", json.dumps(doc).encode()), ("meshes/ball.ply", PLY)])
    if kind == "nested":
        depth = draw(st.integers(100, 300_000))
        body = b'{"meshes": ' + b"[" * depth + b"]" * depth + b"}"
        return kind, _zip([("scene.json", body)]) if draw(st.booleans()) else body
    if kind == "huge json":
        n = draw(st.integers(10_000, 400_000))
        return kind, json.dumps({"meshes": [], "instances": [[0.5] * 4] * n}).encode()
    if kind == "zip of many":
        n = draw(st.integers(1, 200))
        return kind, _zip([("scene.json", json.dumps(_scene_doc()).encode())]
                          + [(f"m/{i}.ply", b"x") for i in range(n)], zipfile.ZIP_STORED)
    return kind, b"glTF" + draw(st.binary(max_size=512))


def test_upload_endpoint_fuzzed(fuzzed):
    statuses: Counter = Counter()
    failures: list[str] = []
    with httpx.Client(base_url=fuzzed.url, timeout=REQUEST_TIMEOUT_S) as client:
        @_fuzz_settings(max_examples=UPLOAD_EXAMPLES)
        @given(upload=uploads(), multipart=st.booleans(), name=st.sampled_from(
            [None, "scene.zip", "x.gltf", "../../x.json", "a" * 300]))
        def run(upload, multipart, name):
            kind, data = upload
            if multipart:
                r = client.post("/v1/scenes", files={"file": (name or "upload", data)})
            else:
                r = client.post("/v1/scenes", content=data, params={"filename": name} if name
                                and len(name) <= 200 else None)
            statuses[(kind, r.status_code)] += 1
            try:
                assert r.status_code in UPLOAD_STATUSES, r.text[:300]
                body = r.json()
                if r.status_code >= 400:
                    problem = Problem.model_validate(body)
                    assert problem.status == r.status_code, body
                    assert r.headers["content-type"] == PROBLEM_MEDIA_TYPE, r.headers
                _check_no_paths(fuzzed, r.text)
            except (AssertionError, ValueError) as e:
                failures.append(f"{kind} -> {r.status_code}: {e}")

        run()
        assert client.get("/healthz").json() == {"status": "ok"}
    summary = "\n".join(f"{k}: {v}" for k, v in sorted(statuses.items(), key=str))
    assert not failures, "\n".join(failures[:20]) + f"\n{summary}"
    assert sum(statuses.values()) >= 400, summary
    # Nothing escaped: every stored scene's files lie inside its own directory.
    scenes = fuzzed.settings.scenes_dir
    for path in scenes.rglob("*"):
        assert not path.is_symlink() and scenes.resolve() in path.resolve().parents
