"""`bench_strong_scaling --merge`: runs cut to fit a short lease become one table and plot,
each row keeping its own run's reference."""

import json

import pytest

from bench.render import bench_strong_scaling as bss


def _row(scene: str, mode: str, k: int, wall: float, ref_wall: float) -> dict:
    shards = [] if k == 0 else [wall] * k
    return {"scene": scene, "mode": mode, "k": k, "render_s": wall, "wall_ratio": wall / ref_wall,
            "cpu_s": wall * max(k, 1), "cpu_ratio": wall * max(k, 1) / ref_wall,
            "coordinator_cpu_s": 0.1 * k, "coordinator_share": 0.01 * k,
            "shard_cpu_s": shards, "wavefront_cpu_s": [0.8 * w for w in shards],
            "busy_fraction": [0.9] * k, "named_cpu_fraction": [0.95] * k, "steps": 10 * k,
            "parcels": 20 * k, "ray_bytes": 1e6 * k, "phase_cpu_s": {}}


def _result(cpu_model: str, rows: list[dict]) -> dict:
    return {"machine": {"cpu_model": cpu_model, "nproc": 16, "ray": "x"}, "rows": rows,
            "settings": {"ks": sorted({r["k"] for r in rows if r["k"]})},
            "targets": bss.TARGETS, "model": {}}


def test_merged_runs_keep_their_own_reference_and_make_one_table_and_plot(tmp_path):
    a = tmp_path / "ss_k8.json"
    b = tmp_path / "ss_city_k4.json"
    a.write_text(json.dumps(_result("Xeon", [_row("city", "reference", 0, 10.0, 10.0),
                                             _row("city", "exact", 8, 4.0, 10.0)])))
    b.write_text(json.dumps(_result("Xeon", [_row("city", "reference", 0, 12.0, 12.0),
                                             _row("city", "exact", 4, 6.0, 12.0)])))
    res = bss.merge([a, b])
    assert [(r["run"], r["mode"], r["k"]) for r in res["rows"]] == [
        ("k8", "reference", 0), ("city_k4", "reference", 0), ("city_k4", "exact", 4),
        ("k8", "exact", 8)]
    assert [r["wall_ratio"] for r in res["rows"] if r["k"]] == [0.5, 0.4]  # each its own ref
    assert set(res["runs"]) == {"k8", "city_k4"}
    table = bss.markdown(res)
    assert "| run | scene |" in table and "| city_k4 | city | exact | 4 |" in table
    bss.plot(res, tmp_path / "merged.png")
    assert (tmp_path / "merged.png").stat().st_size > 1000


def test_runs_from_different_cpus_are_not_merged(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(_result("Xeon", [_row("city", "exact", 2, 5.0, 10.0)])))
    b.write_text(json.dumps(_result("EPYC", [_row("city", "exact", 4, 5.0, 10.0)])))
    with pytest.raises(SystemExit, match="different CPUs"):
        bss.merge([a, b])


def test_a_bracketed_reference_gives_ratios_against_the_mean_of_its_runs():
    ref = _row("forest", "reference", 0, 12.0, 12.0)
    row = _row("forest", "exact", 8, 5.0, 12.0)
    bss._bracket(ref, [_row("forest", "reference", 0, 14.0, 14.0)])
    bss._ratios(row, ref)
    assert ref["render_s_runs"] == [12.0, 14.0] and ref["render_s"] == 13.0
    assert row["wall_ratio"] == round(5.0 / 13.0, 3) and row["cpu_ratio"] == round(40 / 13, 3)
    table = bss.markdown(_result("Xeon", [ref, row]))
    assert "forest 12.00, 14.00 s" in table
