"""The demo scene cache: demos written by other versions of the generators are listed and
deleted only on request (`nprt scenes --prune`); the current version and anything that is
not a demo directory stay."""

from __future__ import annotations

import logging

from nprt.scene.store import demo_dir, materialize_demo, stale_demos
from nprt.service.cli import main


def test_prune_deletes_only_older_versions_of_demos(tmp_path, monkeypatch, capsys, caplog):
    monkeypatch.setenv("NPRT_SCENE_CACHE", str(tmp_path))
    current = demo_dir("forest", "tiny")
    stale = tmp_path / "forest-tiny-s0-0123456789ab"
    keep = [tmp_path / "my-own-scene", tmp_path / ".forest-tiny-s0-abc123",  # not a demo;
            tmp_path / "nosuchdemo-tiny-s0-0123456789ab"]  # being written; unknown name
    for d in (stale, *keep):
        (d / "meshes").mkdir(parents=True)
        (d / "scene.json").write_text("{}")
        (d / "meshes" / "m.ply").write_bytes(b"x" * 1000)
    with caplog.at_level(logging.WARNING, logger="nprt.scene.store"):
        materialize_demo("forest", "tiny")  # warns about the stale demo, deletes nothing
    assert "nprt scenes --prune" in caplog.text and stale.is_dir()
    assert [d for d, _ in stale_demos()] == [stale]

    assert main(["scenes", "--prune"]) == 0
    out = capsys.readouterr().out
    assert f"deleted {stale}" in out and "1 stale demos deleted" in out
    assert not stale.exists()
    assert all(d.is_dir() for d in (current, *keep))
    assert stale_demos() == []
