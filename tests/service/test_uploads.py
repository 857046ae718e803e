"""Zip member paths: what may be extracted and what is refused before any write."""

from __future__ import annotations

import io
import warnings
import zipfile
from pathlib import PurePosixPath

import pytest

from nprt.service.errors import BadUpload
from nprt.service.uploads import find_entry, safe_member_path
from tests.service.helpers import LiveServer, problem_detail, settings_for


@pytest.mark.parametrize("name", ["scene.json", "meshes/a.ply", "a/b/c.ply", "dir/"])
def test_safe_member_path_accepts_relative_paths(name):
    assert safe_member_path(name) == PurePosixPath(name)
    assert ".." not in safe_member_path(name).parts


@pytest.mark.parametrize("name,why", [
    ("../x", "'..' path parts"), ("a/../../x", "'..' path parts"), ("/etc/passwd", "absolute"),
    ("C:/x", "absolute"), ("a\\..\\x", "backslashes"), ("a\x00b", "NUL")])
def test_safe_member_path_refuses_escapes(name, why):
    with pytest.raises(BadUpload, match=why):
        safe_member_path(name)


def test_find_entry_prefers_the_shallowest_json():
    files = [PurePosixPath(p) for p in ("meshes/m.glb", "sub/other.json", "scene.json")]
    assert find_entry(files) == PurePosixPath("scene.json")
    with pytest.raises(BadUpload, match="several candidate scene files: a.json, b.json"):
        find_entry([PurePosixPath("a.json"), PurePosixPath("b.json")])


def _zip(members: list[tuple[str, bytes]], method: int = zipfile.ZIP_STORED) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns about the duplicate names we want
        with zipfile.ZipFile(buf, "w", method) as zf:
            for name, data in members:
                zf.writestr(name, data)
    return buf.getvalue()


SCENE = b'{"meshes": []}'


def _bad_crc() -> bytes:
    data = bytearray(_zip([("scene.json", SCENE), ("mesh.ply", b"ply data here")]))
    at = data.find(b"ply data here")
    data[at] ^= 0xFF
    return bytes(data)


def _bad_deflate() -> bytes:
    payload = bytes(range(256)) * 64
    data = bytearray(_zip([("scene.json", SCENE), ("mesh.bin", payload)], zipfile.ZIP_DEFLATED))
    second = data.find(b"PK\x03\x04", 4)
    start = second + 30 + len("mesh.bin")
    data[start:start + 16] = b"\xff" * 16
    return bytes(data)


def _flag_encrypted(data: bytes) -> bytes:
    out = bytearray(data)
    for sig, off in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):
        at = out.find(sig)
        while at >= 0:
            out[at + off] |= 0x1
            at = out.find(sig, at + 4)
    return bytes(out)


def _method(data: bytes, method: int) -> bytes:
    out = bytearray(data)
    for sig, off in ((b"PK\x03\x04", 8), (b"PK\x01\x02", 10)):
        at = out.find(sig)
        while at >= 0:
            out[at + off:at + off + 2] = method.to_bytes(2, "little")
            at = out.find(sig, at + 4)
    return bytes(out)


LONG_PART = "p" * 300
MEMBER_ERRORS = {
    "bad CRC": (_bad_crc(), "'mesh.ply': cannot be extracted: BadZipFile: Bad CRC-32"),
    "broken deflate stream": (_bad_deflate(), "'mesh.bin': cannot be extracted"),
    "unsupported compression": (_method(_zip([("scene.json", SCENE)]), 99),
                                "'scene.json': compression method 99 is not supported"),
    "encrypted member": (_flag_encrypted(_zip([("scene.json", SCENE)])),
                         "'scene.json': encrypted members are not supported"),
    "duplicate names": (_zip([("scene.json", SCENE), ("scene.json", SCENE)]),
                        "'scene.json': duplicate name"),
    "file and directory": (_zip([("scene.json", SCENE), ("m", b"x"), ("m/", b"")]),
                           "'m/': is both a file and a directory"),
    "file under a file": (_zip([("scene.json", SCENE), ("m", b"x"), ("m/a.ply", b"x")]),
                          "'m/a.ply': lies under 'm', which is a file"),
    "member named dot": (_zip([("scene.json", SCENE), (".", b"x")]),
                         "'.': an empty or '.' name is not allowed"),
    "over-long part": (_zip([("scene.json", SCENE), (f"{LONG_PART}.ply", b"x")]),
                       f"'{LONG_PART}.ply': a path part is over 255 bytes"),
    "over-long name": (_zip([("scene.json", SCENE), ("d/" * 600 + "m.ply", b"x")]),
                       "names are limited to 1024 bytes"),
    "truncated archive": (_zip([("scene.json", SCENE)])[:40], "not a readable zip file"),
    "deeply nested JSON": (b'{"a": ' + b"[" * 200_000 + b"]" * 200_000 + b"}",
                           "is JSON nested too deeply to read"),
}


@pytest.mark.parametrize("case", sorted(MEMBER_ERRORS))
def test_every_member_error_is_a_400_naming_the_member(client, case):
    data, expected = MEMBER_ERRORS[case]
    r = client.post("/v1/scenes", content=data, params={"filename": "upload.zip"})
    assert r.status_code == 400, r.text
    assert expected in problem_detail(r), r.json()
    assert "/tmp" not in problem_detail(r) and "/work" not in problem_detail(r)


def test_leftover_upload_files_are_removed_at_start(tmp_path):
    settings = settings_for(tmp_path)
    stale = settings.tmp_dir / "upload-killed" / "upload"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"x" * 1000)
    with LiveServer(settings):
        assert settings.tmp_dir.is_dir() and list(settings.tmp_dir.iterdir()) == []
