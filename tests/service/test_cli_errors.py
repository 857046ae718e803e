"""Every bad input or option to `nprt render` gets one line `nprt: <what>: <where>: <why>`
and a non-zero exit, before any rendering: nothing here renders a pixel."""

from __future__ import annotations

import json
import os
import resource
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from nprt.service.cli import main
from nprt.service.preflight import CliError, check_memory, estimate_memory
from nprt.service.ray_reach import check_ray_reachable, ray_endpoint
from nprt.workers.settings import RenderSettings

TRI = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}
ROOT = Path(__file__).resolve().parents[2]


def _one_line(capsys, rc: int, expected: str) -> str:
    """The run failed with exactly one stderr line (no traceback, no progress bar)."""
    err = capsys.readouterr().err
    assert rc != 0
    assert err.count("\n") == 1 and err.startswith("nprt: "), err
    assert expected in err, err
    return err.strip()


def _scene(tmp_path, faces=None) -> str:
    doc = {"meshes": [{"name": "t", **TRI, **({"faces": faces} if faces else {})}],
           "instances": [{"mesh": "t"}]}
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    return str(tmp_path / "scene.json")


def test_deeply_nested_json_is_one_scene_error(tmp_path, capsys):
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    rc = main(["render", str(tmp_path / "deep.json")])
    _one_line(capsys, rc, "deep.json: JSON nested too deeply to read")


@pytest.mark.parametrize("kind", ["fifo", "directory", "loop"])
def test_scene_file_that_is_not_a_file_says_what_it_is(tmp_path, capsys, kind):
    path = tmp_path / "scene.json"
    {"fifo": os.mkfifo, "directory": os.mkdir,
     "loop": lambda p: os.symlink(p, p)}[kind](path)
    rc = main(["render", str(path)])
    line = _one_line(capsys, rc, "scene.json: scene file ")
    assert {"fifo": "is a FIFO", "directory": "is a directory",
            "loop": "is a symlink loop"}[kind] in line
    assert "not found" not in line


@pytest.mark.parametrize(("index", "expected"), [
    (2**70, f"face index {2**70} out of range for 3 vertices"),
    (2**32, f"face index {2**32} out of range for 3 vertices"),  # would wrap to 0 in uint32
    (2**63, f"face index {2**63} out of range for 3 vertices"),  # numpy makes this a float
    (-1, "meshes[0].faces[0][2]: Input should be greater than or equal to 0"),
])
def test_face_index_out_of_range_is_named_exactly(tmp_path, capsys, index, expected):
    rc = main(["render", _scene(tmp_path, faces=[[0, 1, index]])])
    line = _one_line(capsys, rc, expected)
    assert "non-negative" not in line


@pytest.mark.parametrize(("flags", "expected"), [
    (["--spp", "0"], "nprt: invalid option: --spp 0: Input should be greater than or equal to 1"),
    (["--width", "0"], "nprt: invalid option: --width 0: Input should be greater than"),
    (["--height", "20000"], "nprt: invalid option: --height 20000: Input should be less than"),
    (["--band", "2"], "nprt: invalid option: --band 2.0: Input should be less than or equal"),
    (["--tile-size", "4"], "nprt: invalid option: --tile-size 4: Input should be greater"),
    (["--proxy-steps", "0"], "nprt: invalid option: --proxy-steps 0: Input should"),
    (["--mode", "proxy"], "nprt: invalid option: settings: mode 'proxy' needs shards >= 1"),
    (["--width", "x"], "nprt: invalid option: nprt render: argument --width: invalid int"),
    (["--mode", "fast"], "nprt: invalid option: nprt render: argument --mode: invalid choice"),
])
def test_bad_option_is_one_line_naming_the_flag(tmp_path, capsys, flags, expected):
    with pytest.raises(SystemExit) as info:  # argparse exits; pydantic errors return
        sys.exit(main(["render", _scene(tmp_path), *flags]))
    line = _one_line(capsys, info.value.code, expected)
    assert "validation error" not in line and "errors.pydantic.dev" not in line


@pytest.mark.parametrize(("flag", "target", "expected"), [
    ("-o", "file/out.png", "file is not a directory"),
    ("-o", "folder", "unknown image type '(none)'"),
    ("-o", "folder.png", "is a directory"),
    ("-o", "out.txt", "unknown image type '.txt'; use .png or .exr"),
    ("--stats", "folder", "is a directory"),
    ("--stats", "file/stats.json", "file is not a directory"),
])
def test_unwritable_output_is_refused_before_the_scene_loads(tmp_path, capsys, flag, target,
                                                             expected):
    (tmp_path / "file").write_text("x")
    (tmp_path / "folder").mkdir()
    (tmp_path / "folder.png").mkdir()
    # The scene does not exist: a refusal naming the output proves it came first.
    rc = main(["render", str(tmp_path / "missing.json"), flag, str(tmp_path / target)])
    line = _one_line(capsys, rc, expected)
    assert f"{flag} {tmp_path / target}" in line and "missing.json" not in line


def test_read_only_output_directory_is_refused(tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root writes anywhere")
    (tmp_path / "ro").mkdir(mode=0o555)
    rc = main(["render", "forest:tiny", "-o", str(tmp_path / "ro" / "sub" / "x.png")])
    _one_line(capsys, rc, "is not writable")


def test_demo_out_that_is_a_file_is_refused(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    rc = main(["demo", "--out", str(tmp_path / "file")])
    _one_line(capsys, rc, f"--out {tmp_path / 'file'}: exists and is not a directory")


def test_memory_estimate_counts_the_film_exactly():
    est = estimate_memory(RenderSettings(width=300, height=200, spp=8, spp_per_pass=4,
                                         tile_size=64))
    assert est.film_bytes == 300 * 200 * (3 * 8 + 8)  # float64 sums + int64 counts
    assert est.inflight_bytes == 64 * 64 * 3 * 8  # the reference holds one pass at a time
    # Passes are never listed: a billion of them cost nothing more.
    huge = estimate_memory(RenderSettings(width=300, height=200, spp=1 << 16, spp_per_pass=1,
                                          tile_size=8))
    assert huge.inflight_bytes == 8 * 8 * 3 * 8
    assert est.total_bytes > est.film_bytes


def test_memory_estimate_of_a_distributed_render_counts_live_passes_once_a_tile():
    from nprt.workers.runtime.coordinator import WINDOW_PER_SHARD

    # 5 x 4 tiles: K = 2 shards would keep more passes live, but one a tile is the limit.
    est = estimate_memory(RenderSettings(width=300, height=200, spp=8, tile_size=64, shards=2))
    assert est.inflight_bytes == 20 * 2 * 64 * 64 * 3 * 8  # a part per shard per live pass
    wide = estimate_memory(RenderSettings(width=3000, height=2000, spp=8, tile_size=64,
                                          shards=2))
    # 1,504 tiles: the window binds
    assert wide.inflight_bytes == WINDOW_PER_SHARD * 2 * 2 * 64 * 64 * 3 * 8


def test_render_that_does_not_fit_is_refused_with_the_estimate():
    s = RenderSettings(width=16384, height=16384)
    with pytest.raises(CliError) as info:
        check_memory(s, available_bytes=6 << 30)
    message = str(info.value)
    assert message.startswith("render too large: --width 16384 --height 16384 --spp 16: ")
    assert "film 8.0 GiB" in message and "only 6.0 GiB of memory is available" in message
    assert check_memory(RenderSettings(), available_bytes=1 << 30).total_bytes < 1 << 30


def test_cli_under_an_address_space_limit_refuses_a_huge_film(tmp_path):
    # A real limit (ulimit -v 8 GiB), not a stubbed probe: the CLI must see it.
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    run = subprocess.run(
        [sys.executable, "-m", "nprt.service.cli", "render", _scene(tmp_path), "--width", "16384",
         "--height", "16384", "-o", str(tmp_path / "big.png")],
        preexec_fn=limit, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1 and "nprt: render too large: --width 16384" in run.stderr
    assert "of memory is available" in run.stderr and not (tmp_path / "big.png").exists()


def test_reference_render_checks_load_neither_ray_nor_grpc(tmp_path):
    # Importing Ray starts gRPC's machinery, which aborted under this limit (CI, load 20+);
    # a render without shards needs neither, refused or not.
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))

    code = ("import sys; from nprt.service.cli import main; rc = main(sys.argv[1:]); "
            "print(rc, sorted(m for m in sys.modules if m.split('.')[0] in ('ray', 'grpc')))")
    run = subprocess.run(
        [sys.executable, "-c", code, "render", _scene(tmp_path), "--width", "16384",
         "--height", "16384", "-o", str(tmp_path / "big.png")],
        preexec_fn=limit, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
        text=True, timeout=120)
    assert run.stdout.split("\n")[-2] == "2 []", (run.stdout, run.stderr)


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_ray_address_fails_fast_naming_it(tmp_path, capsys):
    address = f"127.0.0.1:{_closed_port()}"
    rc = main(["render", _scene(tmp_path), "--shards", "1", "--ray-address", address])
    _one_line(capsys, rc, f"nprt: cannot reach Ray: --ray-address {address}: nothing answers "
                          f"there (Connection refused)")


def test_silent_listener_is_not_taken_for_ray():
    with socket.socket() as silent:  # accepts TCP, never answers: ray.init would hang
        silent.bind(("127.0.0.1", 0))
        silent.listen(4)
        address = f"127.0.0.1:{silent.getsockname()[1]}"
        with pytest.raises(CliError, match=rf"--ray-address {address}: no answer within 0.5 s"):
            check_ray_reachable(address, timeout_s=0.5)


@pytest.mark.parametrize(("address", "expected"), [
    ("auto", None), ("local", None), ("10.0.0.1:6379", "10.0.0.1:6379"),
    ("ray://head:10001", "head:10001"), ("[::1]:6379", "[::1]:6379")])
def test_ray_endpoint_parses_what_ray_init_takes(address, expected):
    assert ray_endpoint(address) == expected


def test_ray_endpoint_refuses_an_address_without_port():
    with pytest.raises(CliError, match="--ray-address head: expected HOST:PORT"):
        ray_endpoint("head")


def test_no_address_means_ray_address_variable(monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert ray_endpoint(None) is None
    monkeypatch.setenv("RAY_ADDRESS", "head:6379")
    assert ray_endpoint(None) == "head:6379"
