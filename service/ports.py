"""The ports `nprt serve` listens on. Its HTTP workers (and gRPC, whose listener sets
SO_REUSEPORT by default) each bind the port with SO_REUSEPORT, and the kernel lets any
process of the same user join such a port. So a second service on a port already in use
would share the connections silently instead of failing: a port is refused when something
answers on it, and the parent holds its ports, bound and not listening, for the service's
life, so that the kernel hands them to no one else (port 0 included)."""

from __future__ import annotations

import socket

from nprt.service.preflight import CliError


def reuseport_socket(host: str, port: int) -> socket.socket:
    """A TCP socket bound to host:port with SO_REUSEPORT (not listening: a socket that does
    not listen gets no connections)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    try:
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock


def connect_target(host: str) -> str:
    """Where a client on this machine reaches a server bound to host."""
    return "127.0.0.1" if host in ("0.0.0.0", "") else "::1" if host == "::" else host


def hold_port(host: str, port: int, what: str) -> socket.socket:
    """Bind host:port (0: one the kernel picks) for `what` ("REST", "gRPC"), not listening;
    CliError where another process answers there or holds it without SO_REUSEPORT."""
    if port:
        try:
            with socket.create_connection((connect_target(host), port), timeout=1.0):
                pass
        except OSError:
            pass
        else:
            raise CliError(f"{what} port", f"{host}:{port}",
                           "another process is serving on it (choose another port, or 0 "
                           "for a free one)")
    try:
        return reuseport_socket(host, port)
    except OSError as e:
        raise CliError(f"{what} port", f"{host}:{port}", e.strerror or str(e)) from None
