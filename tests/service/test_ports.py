"""`nprt serve` refuses a port another process serves, even one whose listener set
SO_REUSEPORT (as another `nprt serve`'s HTTP workers and gRPC do), where binding alone would
succeed and the two services would share the connections."""

from __future__ import annotations

import socket

import pytest

from nprt.service.cli import main
from nprt.service.ports import hold_port, reuseport_socket
from nprt.service.preflight import CliError


def _listener(reuseport: bool) -> socket.socket:
    sock = reuseport_socket("127.0.0.1", 0) if reuseport else socket.socket()
    if not reuseport:
        sock.bind(("127.0.0.1", 0))
    sock.listen(4)
    return sock


def test_a_port_another_reuseport_service_serves_is_refused():
    with _listener(reuseport=True) as other:
        port = other.getsockname()[1]
        with reuseport_socket("127.0.0.1", port):  # the kernel would let it share
            pass
        with pytest.raises(CliError, match=f"REST port: 127.0.0.1:{port}: another process "
                                           "is serving on it"):
            hold_port("127.0.0.1", port, "REST")


def test_a_port_bound_without_reuseport_is_refused_with_the_system_reason():
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))  # bound, not listening: nothing answers
        port = other.getsockname()[1]
        with pytest.raises(CliError, match=f"gRPC port: 127.0.0.1:{port}: Address already"):
            hold_port("127.0.0.1", port, "gRPC")


def test_a_held_port_is_kept_from_everyone_else():
    with hold_port("127.0.0.1", 0, "REST") as held:
        port = held.getsockname()[1]
        assert port != 0
        with socket.socket() as other, pytest.raises(OSError):
            other.bind(("127.0.0.1", port))


@pytest.mark.parametrize("flag", ["--port", "--grpc-port"])
def test_serve_on_a_served_port_fails_in_one_line_before_starting_anything(
        tmp_path, capsys, flag):
    with _listener(reuseport=True) as other:
        port = other.getsockname()[1]
        other_flag = {"--port": ["--grpc-port", "-1"], "--grpc-port": ["--port", "0"]}[flag]
        rc = main(["serve", flag, str(port), *other_flag, "--data-dir", str(tmp_path / "d")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.strip().splitlines()[-1] == (
        f"nprt: {'REST' if flag == '--port' else 'gRPC'} port: 127.0.0.1:{port}: another "
        "process is serving on it (choose another port, or 0 for a free one)"), err
    assert not (tmp_path / "d" / "jobs").exists()
