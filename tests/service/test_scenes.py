"""REST /v1/scenes: uploads (GLB, zip of JSON + meshes), limits, zip-slip, validation."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile

import httpx
import numpy as np
import pytest
import trimesh

from nprt.scene.errors import UnsafePath
from nprt.service.scenes import SceneStore
from tests.scene._util import recording_opens
from tests.service.helpers import LiveServer, problem_detail, settings_for

LIMIT_BYTES = 64 * 1024


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A server with a small upload limit; its data dir sits inside `root`."""
    root = tmp_path_factory.mktemp("scenes")
    with LiveServer(settings_for(root, max_upload_bytes=LIMIT_BYTES,
                                 max_extracted_bytes=4 * LIMIT_BYTES)) as server, \
            httpx.Client(base_url=server.url, timeout=30.0) as client:
        yield client, root


def _zip(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _scene_zip(extra: dict[str, bytes] | None = None, instances=None,
               mesh_path: str = "meshes/ball.ply", texture: str | None = None) -> bytes:
    ply = trimesh.creation.icosphere(subdivisions=1).export(file_type="ply")
    doc = {"name": "zipped", "meshes": [{"name": "ball", "path": mesh_path}],
           "instances": instances if instances is not None else [
               {"mesh": "ball", "translate": [0, 0, 0]}, {"mesh": "ball", "translate": [2, 0, 0]}],
           "environment": {"kind": "constant", "radiance": [1, 1, 1]}}
    if texture is not None:
        doc["materials"] = [{"name": "m", "texture": texture}]
        doc["meshes"][0]["material"] = "m"
    return _zip({"scene.json": json.dumps(doc).encode(), "meshes/ball.ply": ply,
                 **(extra or {})})


def _post(client, body, **headers) -> httpx.Response:
    return client.post("/v1/scenes", content=body,
                       headers={"Content-Type": "application/zip", **headers})


def _stored(root):
    return sorted(p.name for p in (root / "data" / "scenes").iterdir())


def test_zip_scene_is_stored_content_addressed_and_listed(small):
    client, root = small
    body = _scene_zip()
    r = _post(client, body)
    assert r.status_code == 201, r.text
    scene = r.json()
    assert scene["id"] == hashlib.sha256(body).hexdigest() and scene["kind"] == "zip"
    assert scene["entry"] == "scene.json"
    assert scene["summary"]["base_meshes"] == 1 and scene["summary"]["instances"] == 2
    again = _post(client, body)
    assert again.status_code == 200 and again.json()["id"] == scene["id"]
    listed = client.get("/v1/scenes").json()
    assert scene["id"] in [s["id"] for s in listed["data"]]
    assert {"forest", "city", "sculpture"} <= {s["id"] for s in listed["data"]}
    got = client.get(f"/v1/scenes/{scene['id']}")
    assert got.status_code == 200 and got.json()["summary"] == scene["summary"]


def test_multipart_glb_upload_is_accepted(small, glb_path):
    client, _ = small
    r = client.post("/v1/scenes", files={"file": (glb_path.name, glb_path.read_bytes())})
    assert r.status_code in (200, 201), r.text
    assert r.json()["kind"] == "glb" and r.json()["filename"] == glb_path.name
    assert r.json()["summary"]["instances"] == 2


def test_upload_over_content_length_limit_is_413(small):
    client, root = small
    r = _post(client, b"PK" + b"\0" * (LIMIT_BYTES + 1))
    assert r.status_code == 413
    assert problem_detail(r) == (f"upload of {LIMIT_BYTES + 3} bytes is larger than the "
                                 f"limit of {LIMIT_BYTES}")


def test_chunked_upload_over_limit_is_413_while_streaming(small):
    client, root = small
    before = _stored(root)

    def chunks():  # no Content-Length: the server must count as bytes arrive
        for _ in range(8):
            yield b"\0" * (LIMIT_BYTES // 4)

    r = client.post("/v1/scenes", content=chunks(), headers={"Content-Type": "application/zip"})
    assert r.status_code == 413
    assert problem_detail(r) == f"upload is larger than the limit of {LIMIT_BYTES} bytes"
    assert _stored(root) == before and list((root / "data" / "tmp").iterdir()) == []


@pytest.mark.parametrize("evil", ["../evil.txt", "meshes/../../evil.txt", "/tmp/evil.txt",
                                  "C:/evil.txt", "..\\evil.txt"])
def test_zip_slip_is_refused_and_nothing_is_written(small, evil):
    client, root = small
    before = _stored(root)
    r = _post(client, _scene_zip({evil: b"pwned"}))
    assert r.status_code == 400
    assert problem_detail(r).startswith(f"zip member {evil!r}")
    assert _stored(root) == before
    assert not list(root.rglob("evil.txt")) and not (root.parent / "evil.txt").exists()
    assert list((root / "data" / "tmp").iterdir()) == []


def test_zip_symlink_is_refused(small):
    client, _ = small
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        info = zipfile.ZipInfo("link")
        info.external_attr = 0o120777 << 16
        zf.writestr(info, "/etc/passwd")
    r = _post(client, buf.getvalue())
    assert r.status_code == 400
    assert problem_detail(r) == "zip member 'link': symlinks are not allowed"


def test_zip_bomb_over_extracted_limit_is_413(small):
    client, _ = small
    body = _scene_zip({"big.bin": b"\0" * (5 * LIMIT_BYTES)})  # compresses to a few KiB
    assert len(body) < LIMIT_BYTES
    r = _post(client, body)
    assert r.status_code == 413 and "extracts to more than" in problem_detail(r)


def test_scene_that_does_not_load_is_422_with_scene_error(small):
    client, root = small
    before = _stored(root)
    r = _post(client, _scene_zip(instances=[{"mesh": "nosuchmesh"}]))
    assert r.status_code == 422
    detail = problem_detail(r)
    assert "nosuchmesh" in detail and str(root) not in detail
    assert _stored(root) == before


def test_unknown_format_is_400(small):
    client, _ = small
    r = _post(client, b"hello, not a scene", **{"Content-Type": "application/octet-stream"})
    assert r.status_code == 400 and "is not a GLB, glTF, JSON scene or zip" in problem_detail(r)


def test_zip_without_scene_file_is_400(small):
    client, _ = small
    r = _post(client, _zip({"readme.txt": b"hi"}))
    assert r.status_code == 400
    assert problem_detail(r) == ("zip holds no scene file (.json, .glb, .gltf); "
                                 "found readme.txt")


def test_demo_scene_has_summary_and_unknown_scene_is_404(small):
    client, _ = small
    r = client.get("/v1/scenes/forest:tiny")
    assert r.status_code == 200 and r.json()["kind"] == "demo"
    assert r.json()["summary"]["instances"] >= 1
    missing = client.get("/v1/scenes/" + "0" * 64)
    assert missing.status_code == 404
    assert problem_detail(missing) == f"no stored scene with id {'0' * 64!r}"


@pytest.fixture(scope="module")
def outside(small):
    """A valid mesh, texture and buffer beside the data dir: what an escape would read."""
    _, root = small
    folder = root / "outside"
    folder.mkdir(exist_ok=True)
    (folder / "secret.ply").write_bytes(trimesh.creation.box().export(file_type="ply"))
    np.save(folder / "secret.npy", np.full((2, 2, 3), 0.5, np.float32))
    return folder


def _escapes(outside):
    # From <data>/tmp/scene-*/content, four '..' reach the folder holding `outside`.
    up = "../" * 4 + "outside/"
    return [("mesh", str(outside / "secret.ply")), ("mesh", up + "secret.ply"),
            ("mesh", "meshes/" + "../" * 5 + "outside/secret.ply"),
            ("texture", str(outside / "secret.npy")), ("texture", up + "secret.npy")]


@pytest.mark.parametrize("case", range(5))
def test_scene_path_leaving_the_upload_is_400_and_nothing_outside_is_read(small, outside,
                                                                           case):
    client, root = small
    field, ref = _escapes(outside)[case]
    body = _scene_zip(mesh_path=ref) if field == "mesh" else _scene_zip(texture=ref)
    before = _stored(root)
    with recording_opens() as opened:
        r = _post(client, body)
    assert r.status_code == 400, r.text
    detail = problem_detail(r)
    assert detail.startswith("scene.json: ") and repr(ref) in detail
    assert "is absolute" in detail if ref.startswith("/") else "leaves the upload" in detail
    assert str(root) not in detail.replace(ref, "")  # no server path but the scene's own
    assert not [p for p in opened if p.startswith(str(outside.resolve()))]
    assert _stored(root) == before and list((root / "data" / "tmp").iterdir()) == []


def test_zip_member_symlink_to_a_mesh_outside_is_refused(small, outside):
    client, root = small
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("scene.json", json.dumps({"meshes": [{"name": "b", "path": "link.ply"}],
                                              "instances": [{"mesh": "b"}]}))
        info = zipfile.ZipInfo("link.ply")
        info.external_attr = 0o120777 << 16
        zf.writestr(info, str(outside / "secret.ply"))
    with recording_opens() as opened:
        r = _post(client, buf.getvalue())
    assert r.status_code == 400 and "symlinks are not allowed" in problem_detail(r)
    assert not [p for p in opened if p.startswith(str(outside.resolve()))]


@pytest.mark.parametrize("where", ["absolute", "dotdot"])
def test_gltf_buffer_leaving_the_upload_is_400(small, outside, where):
    client, _ = small
    files = trimesh.creation.box().export(file_type="gltf")
    doc = json.loads(files["model.gltf"])
    (outside / "secret.bin").write_bytes(files[doc["buffers"][0]["uri"]])
    uri = str(outside / "secret.bin") if where == "absolute" else "../" * 4 + "outside/secret.bin"
    doc["buffers"][0]["uri"] = uri
    with recording_opens() as opened:
        r = client.post("/v1/scenes", params={"filename": "box.gltf"},
                        content=json.dumps(doc).encode(),
                        headers={"Content-Type": "model/gltf+json"})
    assert r.status_code == 400, r.text
    assert problem_detail(r).startswith("box.gltf: referenced file path ")
    assert repr(uri) in problem_detail(r)
    assert not [p for p in opened if p.startswith(str(outside.resolve()))]


def test_stored_scene_with_a_planted_symlink_is_refused_at_load(tmp_path):
    # Defence in depth: a job loads a stored scene confined to its own folder too.
    settings = settings_for(tmp_path)
    body = _scene_zip()
    SceneStore(settings).ingest(_write(tmp_path / "up.zip", body), "a" * 64, len(body), None)
    (tmp_path / "secret.ply").write_bytes(trimesh.creation.box().export(file_type="ply"))
    mesh = settings.scenes_dir / ("a" * 64) / "content" / "meshes" / "ball.ply"
    mesh.unlink()
    mesh.symlink_to(tmp_path / "secret.ply")
    store = SceneStore(settings)  # a fresh cache, as after a restart
    with recording_opens() as opened, pytest.raises(UnsafePath, match="through a symlink"):
        store.load("a" * 64)
    assert str((tmp_path / "secret.ply").resolve()) not in opened


def _write(path, data: bytes):
    path.write_bytes(data)
    return path
