"""`nprt proxy train` on a mesh file prints the held-out accuracy report."""

from __future__ import annotations

import pytest
import trimesh

from nprt.proxies.cli import main


def test_proxy_train_on_a_mesh_file_prints_the_report_and_caches(tmp_path, capsys):
    pytest.importorskip("torch", reason="training needs PyTorch")
    path = tmp_path / "ball.ply"
    # subdivisions=3: 38 kB of triangles, more than a width-16 proxy (~14 kB), so not skipped
    trimesh.creation.icosphere(subdivisions=3).export(path)
    args = ["proxy", "train", str(path), "--width", "16", "--steps", "200",
            "--samples", "8192", "--out", str(tmp_path / "cache")]
    assert main(args) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| ball"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == "16" and 0.5 < float(cells[3]) <= 1.0
    assert len(list((tmp_path / "cache").glob("*.nprx"))) == 1
    assert main(args) == 0  # second run: served from the cache


def test_proxy_train_skips_a_mesh_lighter_than_its_proxy(tmp_path, capsys):
    path = tmp_path / "pebble.ply"
    trimesh.creation.icosphere(subdivisions=1).export(path)  # 2.4 kB of triangles
    assert main(["proxy", "train", str(path), "--width", "16", "--out", str(tmp_path)]) == 0
    assert "pebble: skipped" in capsys.readouterr().out
    assert not list(tmp_path.glob("*.nprx"))
