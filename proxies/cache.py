"""Proxies on disk, keyed by mesh content hash + config key: the user cache first, then the
proxies shipped with nprt. Bad files are skipped (and retrained); training needs torch."""

from __future__ import annotations

import json
import logging
import os
import tempfile
from pathlib import Path

from nprt.proxies.config import ProxyConfig
from nprt.proxies.inference import Proxy, ProxyFormatError
from nprt.scene.model import Mesh

log = logging.getLogger(__name__)

DEFAULT_DIR = Path(os.environ.get("NPRT_PROXY_CACHE", "~/.cache/nprt/proxies")).expanduser()
SHIPPED_DIR = Path(__file__).resolve().parent / "shipped"
SUFFIX = ".nprx"
# Beside each proxy file: its training's wall-clock figures (Proxy.timing), which vary run
# to run and so are not part of the (reproducible) proxy bytes.
TIMING_SUFFIX = ".timing.json"


class ProxyUnavailable(RuntimeError):
    """No proxy can be had for a mesh (none cached, and training is impossible); the
    renderer then traces that mesh exactly and records this message."""


def _load_trainer():
    """The training entry point; importing it imports torch (an optional extra)."""
    from nprt.proxies.train import train_proxy

    return train_proxy


def file_name(mesh: Mesh, config: ProxyConfig) -> str:
    return f"{mesh.content_hash}-{config.key}{SUFFIX}"


class ProxyCache:
    """dir : user cache directory (default ~/.cache/nprt/proxies or $NPRT_PROXY_CACHE);
    shipped_dir : read-only fallback (None to ignore); threads : onnxruntime threads per
    session of the proxies it returns."""

    def __init__(self, dir=None, shipped_dir=SHIPPED_DIR, threads: int = 1):
        self.dir = Path(dir).expanduser() if dir is not None else DEFAULT_DIR
        self.shipped_dir = Path(shipped_dir) if shipped_dir is not None else None
        self.threads = threads
        self.rejected: list[tuple[str, str]] = []  # (path, why) of files found unusable

    def __repr__(self) -> str:
        return f"ProxyCache(dir={str(self.dir)!r}, shipped_dir={str(self.shipped_dir)!r})"

    def _load(self, path: Path, mesh: Mesh, config: ProxyConfig) -> Proxy | None:
        try:
            proxy = Proxy.from_bytes(path.read_bytes(), threads=self.threads)
        except (OSError, ProxyFormatError) as e:
            return self._reject(path, str(e))
        meta = proxy.meta
        if meta.get("content_hash") != mesh.content_hash:
            return self._reject(path, f"mesh hash {str(meta.get('content_hash'))[:12]} is not "
                                      f"{mesh.content_hash[:12]}")
        if meta.get("config_key") != config.key:
            return self._reject(path, f"config key {meta.get('config_key')} is not {config.key}")
        try:
            proxy.timing = json.loads(path.with_suffix(TIMING_SUFFIX).read_text())
        except (OSError, ValueError):
            pass  # timing is informative only; a proxy without it is as good
        return proxy

    def _reject(self, path: Path, why: str) -> None:
        log.warning("ignoring proxy cache file %s: %s", path, why)
        self.rejected.append((str(path), why))
        return None

    def get(self, mesh: Mesh, config: ProxyConfig) -> Proxy | None:
        """A verified cached proxy for (mesh, config), or None."""
        name = file_name(mesh, config)
        for d in (self.dir, self.shipped_dir):
            if d is not None and (d / name).is_file():
                proxy = self._load(d / name, mesh, config)
                if proxy is not None:
                    return proxy
        return None

    def put(self, mesh: Mesh, config: ProxyConfig, proxy: Proxy) -> Path | None:
        """Write atomically into the user dir; returns the path (None if it is not writable)."""
        if proxy.meta.get("content_hash") != mesh.content_hash:
            raise ValueError(f"proxy is for mesh {str(proxy.meta.get('content_hash'))[:12]}, "
                             f"not {mesh.content_hash[:12]} ({mesh.name!r})")
        path = self.dir / file_name(mesh, config)
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.dir, suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                f.write(proxy.to_bytes())
            os.replace(tmp, path)
            if proxy.timing:
                path.with_suffix(TIMING_SUFFIX).write_text(json.dumps(proxy.timing, indent=1))
        except OSError as e:
            log.warning("could not write proxy cache file %s: %s", path, e)
            return None
        return path

    def get_or_train(self, mesh: Mesh, config: ProxyConfig, progress: bool = True,
                     geometry=None) -> Proxy:
        """The cached proxy, or a freshly trained one (then cached). Raises ProxyUnavailable
        when none is cached and torch is not installed."""
        proxy = self.get(mesh, config)
        if proxy is not None:
            return proxy
        try:
            train = _load_trainer()
        except ImportError as e:
            raise ProxyUnavailable(
                f"no cached proxy for mesh {mesh.name!r} ({mesh.content_hash[:12]}, width "
                f"{config.width}) and training needs PyTorch, which is not importable ({e}); "
                f"install the 'train' extra (pip install 'nprt[train]') or fill the cache"
            ) from e
        trained = train(mesh, config, progress=progress, geometry=geometry)
        proxy = Proxy.from_bytes(trained.to_bytes(), threads=self.threads)
        proxy.timing = dict(trained.timing)
        self.put(mesh, config, proxy)
        return proxy
