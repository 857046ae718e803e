"""`nprt serve` runs gRPC in a child process of its own: REST answers only once gRPC does,
both serve one store, and stopping `serve` stops the child."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import grpc
import httpx
from grpc_health.v1 import health_pb2, health_pb2_grpc

from nprt.protos import nprt_pb2 as pb
from nprt.protos import nprt_pb2_grpc
from tests.service.helpers import REPO, TINY, logged, start_serve


def _children(pid: int) -> dict[int, str]:
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            try:
                out[int(child)] = Path(f"/proc/{child}/cmdline").read_bytes().replace(
                    b"\0", b" ").decode()
            except OSError:  # ended meanwhile
                pass
    return out


def test_serve_runs_grpc_in_a_child_on_the_same_store_and_stops_it(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("NPRT_API_TOKEN", None)
    log_path = tmp_path / "serve.log"
    proc, url = start_serve(["--api-only", "--grpc-port", "0", "--data-dir",
                             str(tmp_path / "data")], log_path, env, 90)
    try:
        # Logged before REST listens: REST answering means gRPC listens already.
        grpc_target = logged(proc, log_path, 0, rb"gRPC on (\S+:\d+)", 1)
        with grpc.insecure_channel(grpc_target) as channel:
            health = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(), timeout=10)
            assert health.status == health_pb2.HealthCheckResponse.SERVING
            job = nprt_pb2_grpc.RenderServiceStub(channel).SubmitJob(
                pb.SubmitJobRequest(scene="forest:tiny",
                                    settings=pb.RenderSettings(**{k: TINY[k] for k in (
                                        "width", "height", "spp")})), timeout=10)
        assert httpx.get(f"{url}/v1/jobs/{job.id}").json()["state"] == "queued"
        children = _children(proc.pid)
        grpc_children = [pid for pid, cmd in children.items() if " grpc " in cmd]
        assert len(grpc_children) == 1, children
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    assert not Path(f"/proc/{grpc_children[0]}").exists() or \
        Path(f"/proc/{grpc_children[0]}/stat").read_text().split(") ")[1][0] == "Z"
