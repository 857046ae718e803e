"""A trained proxy at render time: the two ONNX nets in one self-checking blob, run by
onnxruntime (this module never imports torch). onnxruntime is imported when a net first
runs: the driver reads and ships proxy blobs without running them."""

from __future__ import annotations

import hashlib
import json
import logging
import struct
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import onnxruntime as ort

from nprt.proxies.encoding import depth_decode, encode, to_proxy_box

log = logging.getLogger(__name__)

MAGIC = b"NPRTPRX\x01"
FORMAT_VERSION = 1
_LEN = struct.Struct("<I")
NETS = ("visibility", "depth")
# Rows per onnxruntime call and intra-op thread. The (rows, width) float32 activations
# of a call should stay in the core's cache: a width-64 net ran 1.6x faster at 4096 rows
# a call than at 65536 on one thread (2.7 against 1.8 M rows/s at 8192 on two threads).
ROWS_PER_THREAD = 4096


class ProxyFormatError(ValueError):
    """A proxy blob that is truncated, corrupted or of an unknown format."""


class Proxy:
    """Visibility and depth nets of one base mesh, with their metadata.

    meta : dict with content_hash, width, blocks, encoding, bounds (2, 3) mesh AABB,
    box (2, 3) proxy box, diag (of the proxy box), threshold, config, report
    threads : onnxruntime intra-op threads per session (1: shards run side by side)
    timing : wall-clock figures of its training (train_s, sample_s, queries_per_s); they
    vary with the load, so they live beside the blob, never in it
    """

    def __init__(self, meta: dict, models: dict[str, bytes], threads: int = 1):
        missing = [k for k in NETS if k not in models]
        if missing:
            raise ValueError(f"proxy needs models {NETS}, missing {missing}")
        self.meta = dict(meta)
        self.models = {k: bytes(models[k]) for k in NETS}
        self.threads = int(threads)
        self.box = np.asarray(self.meta["box"], np.float64).reshape(2, 3)
        self.diag = np.float32(self.meta["diag"])
        self._sessions: dict[str, ort.InferenceSession] = {}
        self._calls: dict = {}
        self._line: tuple | None = None
        self._blob: bytes | None = None
        self.timing: dict[str, float] = {}

    def __repr__(self) -> str:
        m = self.meta
        return (f"Proxy(mesh={m.get('content_hash', '?')[:12]}, width={m.get('width')}, "
                f"{self.nbytes} bytes)")

    def __reduce__(self):  # sessions do not pickle; the blob rebuilds them (ray.put)
        return (_from_bytes, (self.to_bytes(), self.threads))

    # ------------------------------------------------------------ container
    def to_bytes(self) -> bytes:
        """MAGIC, u32 header length, JSON header (with the payload's sha256), payload."""
        if self._blob is None:
            payload = b"".join(self.models[k] for k in NETS)
            header = {
                "format": FORMAT_VERSION,
                "sizes": {k: len(self.models[k]) for k in NETS},
                "payload_sha256": hashlib.sha256(payload).hexdigest(),
                "meta": self.meta,
            }
            hb = json.dumps(header, sort_keys=True).encode()
            self._blob = MAGIC + _LEN.pack(len(hb)) + hb + payload
        return self._blob

    @classmethod
    def from_bytes(cls, blob: bytes, threads: int = 1) -> Proxy:
        """Parse and verify a blob; raises ProxyFormatError naming what is wrong."""
        blob = bytes(blob)
        if blob[: len(MAGIC)] != MAGIC:
            raise ProxyFormatError(f"not a proxy blob (magic {blob[:len(MAGIC)]!r})")
        start = len(MAGIC) + _LEN.size
        if len(blob) < start:
            raise ProxyFormatError(f"truncated proxy blob ({len(blob)} bytes)")
        (hlen,) = _LEN.unpack_from(blob, len(MAGIC))
        if len(blob) < start + hlen:
            raise ProxyFormatError(f"truncated proxy blob ({len(blob)} bytes, header alone "
                                   f"needs {start + hlen})")
        try:
            header = json.loads(blob[start:start + hlen])
            sizes = {k: int(header["sizes"][k]) for k in NETS}
            digest, meta = header["payload_sha256"], header["meta"]
        except (ValueError, KeyError, TypeError) as e:
            raise ProxyFormatError(f"bad proxy header: {e}") from None
        if header.get("format") != FORMAT_VERSION:
            raise ProxyFormatError(f"proxy format {header.get('format')}, "
                                   f"expected {FORMAT_VERSION}")
        payload = blob[start + hlen:]
        if len(payload) != sum(sizes.values()):
            raise ProxyFormatError(f"proxy payload is {len(payload)} bytes, header says "
                                   f"{sum(sizes.values())} (truncated?)")
        if hashlib.sha256(payload).hexdigest() != digest:
            raise ProxyFormatError("proxy payload sha256 does not match its header (corrupted)")
        models, off = {}, 0
        for k in NETS:
            models[k] = payload[off:off + sizes[k]]
            off += sizes[k]
        proxy = cls(meta, models, threads)
        proxy._blob = blob
        return proxy

    @property
    def nbytes(self) -> int:
        """Bytes a shard receives for this proxy (the whole blob)."""
        return len(self.to_bytes())

    # ------------------------------------------------------------ inference
    def session(self, net: str) -> ort.InferenceSession:
        if net not in self._sessions:
            import onnxruntime as ort

            opts = ort.SessionOptions()
            opts.intra_op_num_threads = self.threads
            opts.inter_op_num_threads = 1
            # A spinning pool of one net's session kept a core from the other net's: with
            # two threads, both nets ran at 0.45-0.75 M queries/s spinning, 0.9-1.0 not.
            opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
            opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
            opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
            self._sessions[net] = ort.InferenceSession(
                self.models[net], opts, providers=["CPUExecutionProvider"])
        return self._sessions[net]

    def run(self, net: str, x: np.ndarray) -> np.ndarray:
        """Raw net output y (n,) float32 for encoded inputs x (n, k) float32 (C-contiguous).
        A row's answer does not depend on the other rows of x: onnxruntime's kernels (MLAS)
        take rows in pairs, and a batch's odd last row went through another kernel that
        differed in the last bits, so an odd batch gets one zero row more."""
        if len(x) == 0:
            return np.zeros(0, np.float32)
        call = self._call(net)
        chunk = self.chunk_rows  # even: only the last call can be odd
        if len(x) <= chunk:
            return _even_call(call, x)
        out = [_even_call(call, x[s:s + chunk]) for s in range(0, len(x), chunk)]
        return np.concatenate(out)

    def run_even(self, net: str, x: np.ndarray) -> np.ndarray:
        """`run` of x (n, k) float32 (C-contiguous) whose n is even, as a caller that lays
        out its rows with `run`'s padding passes them (nprt.workers.routing.net_rows): no
        copy to pad. Returns y (n,) float32."""
        n = len(x)
        if n % 2:
            raise ValueError(f"run_even needs an even number of rows, got {n}")
        call = self._call(net)
        chunk = self.chunk_rows
        if n <= chunk:
            return call(x).reshape(-1)
        return np.concatenate([call(x[s:s + chunk]).reshape(-1) for s in range(0, n, chunk)])

    @property
    def chunk_rows(self) -> int:
        """Rows per onnxruntime call (`run` splits larger inputs)."""
        return ROWS_PER_THREAD * max(1, self.threads)

    def calls(self, n: int) -> int:
        """onnxruntime calls `run` makes for n rows."""
        return -(-n // self.chunk_rows)

    def _call(self, net: str):
        """The net's caller (`_caller`), made on first use and kept."""
        call = self._calls.get(net)
        if call is None:
            call = self._calls[net] = self._caller(net)
        return call

    def _caller(self, net: str):
        """x -> the net's first output. The session's own binding where there is one: the
        Python wrapper's checks of names and arguments cost 10-15 us a call, as much as a
        call of a width-16 net on 50 rows, and shards make tens of thousands of calls."""
        sess = self.session(net)
        name = sess.get_inputs()[0].name
        outputs = [sess.get_outputs()[0].name]
        inner = getattr(sess, "_sess", None)
        if inner is None or not hasattr(inner, "run"):
            return lambda x: sess.run(outputs, {name: x})[0]
        return lambda x: inner.run(outputs, {name: x}, None)[0]

    def query(self, points: np.ndarray, directions: np.ndarray,
              min_visibility: float | None = None):
        """Predict the first hit of rays entering the box.

        points     : (n, 3) float32, local points on the mesh's box surface
        directions : (n, 3) float32, local unit directions pointing into the box
        min_visibility : evaluate depth only where visibility >= this (t = inf elsewhere)
        returns visibility (n,) float32 in [0, 1], t (n,) float32 distance from each point
        along its direction (meaningful where visibility >= threshold)
        """
        points = np.asarray(points, np.float32)
        directions = np.asarray(directions, np.float32)
        if points.ndim != 2 or points.shape[1] != 3 or directions.shape != points.shape:
            raise ValueError(f"points and directions must both be (n, 3), got "
                             f"{points.shape} and {directions.shape}")
        n = len(points)
        if n == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.float32)
        enc = self.meta["encoding"]
        if enc == "line":  # compiled, the same bits (nprt.proxies.lineenc)
            from nprt.proxies import lineenc

            x, p, shift = lineenc.line_inputs(*self.line_constants()[:4], points, directions)
        else:
            p, shift = to_proxy_box(self.box, points, directions)
            x = encode(self.box, p, directions, enc)
        vis = self.run("visibility", x)
        if min_visibility is None:
            rows = slice(None)
            t = np.empty(n, np.float32)
        else:
            rows = np.flatnonzero(vis >= min_visibility)
            t = np.full(n, np.inf, np.float32)
        y = self.run("depth", x[rows])
        if enc == "line":
            scale, centre = self.line_constants()[4:]
            t[rows] = lineenc.line_depth(scale, centre, p[rows], directions[rows], y,
                                         shift[rows])
        else:
            t_box = depth_decode(self.box, p[rows], directions[rows], y, enc)
            t[rows] = np.maximum(t_box + shift[rows], 0.0)
        return vis, t

    def line_constants(self) -> tuple:
        """The box's float32 constants of encoding.to_proxy_box / encode ("line": lo, hi,
        centre, half diagonal) and of depth_decode (diagonal, centre), computed as they do."""
        if self._line is None:
            lo, hi = self.box.astype(np.float32)
            self._line = (lo, hi, (0.5 * (lo + hi)).astype(np.float32),
                          np.float32(0.5 * np.linalg.norm(hi - lo)),
                          np.float32(np.linalg.norm(self.box[1] - self.box[0])),
                          (0.5 * (self.box[0] + self.box[1])).astype(np.float32))
        return self._line


def _even_call(call, x: np.ndarray) -> np.ndarray:
    """call's (n,) float32 answer for x (n, k), run on an even number of rows."""
    n = len(x)
    if n % 2:
        x = np.concatenate([x, np.zeros((1, x.shape[1]), x.dtype)])
    return call(x).reshape(-1)[:n].astype(np.float32, copy=False)


def _from_bytes(blob: bytes, threads: int) -> Proxy:
    """Unpickling hook. A plain module function: cloudpickle (ray.put) would pickle the
    bound classmethod by value, module globals and all."""
    return Proxy.from_bytes(blob, threads)
