"""`nprt proxy train` on a mesh file prints the held-out accuracy report."""

from __future__ import annotations

import pytest
import trimesh

from proxies.cli import main


def test_proxy_train_on_a_mesh_file_prints_the_report_and_caches(tmp_path, capsys):
    pytest.importorskip("torch", reason="training needs PyTorch")
    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    args = ["proxy", "train", str(path), "--width", "16", "--budget-s", "2",
            "--samples", "8192", "--out", str(tmp_path / "cache")]
    assert main(args) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| ball"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == "16" and 0.5 < float(cells[3]) <= 1.0
    assert len(list((tmp_path / "cache").glob("*.nprx"))) == 1
    assert main(args) == 0  # second run: served from the cache
