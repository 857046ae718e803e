"""Zip member paths: what may be extracted and what is refused before any write."""

from __future__ import annotations

from pathlib import PurePosixPath

import pytest

from service.errors import BadUpload
from service.uploads import find_entry, safe_member_path


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
