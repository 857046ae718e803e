"""Model only what a scene requires: per base mesh, no proxy, exact replication, the
narrowest proxy that meets the accuracy target, or an exact fallback with the reason."""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from nprt.proxies.cache import ProxyCache, ProxyUnavailable
from nprt.proxies.config import DEFAULT_WIDTHS, ProxyConfig, estimate_proxy_bytes
from nprt.proxies.inference import Proxy

log = logging.getLogger(__name__)

DECISIONS = ("none", "replicate", "proxy", "fallback")
# Where no width meets the target, a wider proxy is kept over a narrower one only for a lead
# in held-out accuracy of more than Z_LEAD standard errors (a conventional level, not tuned).
# A wider net costs more at every query it answers (its rows grow with width squared), and
# what a job's accuracy target needs beyond the proxy's answers, its bands send to exact
# tracing. On the held-out foliage scene the old rule (the most accurate, whatever its lead)
# kept width 64 for +0.2 points at 1.6-1.9x the proxy phase's CPU, for no better image
# (bench/README.md, "Proxy width at a job's accuracy target").
Z_LEAD = 2.0


@dataclass
class ProxyDecision:
    """What one base mesh gets. tried : width -> held-out accuracy of each proxy looked at."""

    mesh: int
    name: str
    content_hash: str
    decision: str
    reason: str
    mesh_bytes: int
    width: int | None = None
    accuracy: float | None = None
    proxy_bytes: int | None = None
    train_s: float | None = None  # wall seconds of its training, where known (informative)
    tried: dict[int, float] = field(default_factory=dict)


@dataclass
class ProxyPlan:
    """decisions : one per base mesh, in mesh order; proxies : mesh index -> Proxy for every
    `proxy` decision; replicated : mesh indices every shard holds exactly."""

    decisions: list[ProxyDecision]
    proxies: dict[int, Proxy]
    replicated: set[int]
    target_accuracy: float

    def decision(self, mesh: int) -> ProxyDecision:
        return self.decisions[mesh]

    def to_dict(self) -> dict:
        """JSON-ready summary for job statistics."""
        counts = {d: sum(x.decision == d for x in self.decisions) for d in DECISIONS}
        return {
            "target_accuracy": self.target_accuracy,
            "counts": counts,
            "proxy_bytes": int(sum(p.nbytes for p in self.proxies.values())),
            "replicated": sorted(self.replicated),
            "decisions": [{**asdict(d), "tried": {str(k): v for k, v in d.tried.items()}}
                          for d in self.decisions],
        }


def _accuracy(proxy: Proxy) -> float:
    return float(proxy.meta.get("report", {}).get("accuracy", 0.0))


def _most_accurate(tried: dict[int, float], widths=None) -> int:
    """The width of widths (default: all of tried) with the best held-out accuracy, the
    narrowest on a tie."""
    return max(tried if widths is None else widths, key=lambda w: (tried[w], -w))


def lead_z(wide: Proxy, narrow: Proxy) -> float:
    """wide's lead in held-out accuracy over narrow's, in standard errors of a difference of
    two proportions over their held-out rays (report "eval_rays"). The two are treated as
    independent samples; they are the same rays for every width of one config, so this
    overstates the error, and a lead judged real is real. inf for a lead without counts
    (proxies reported before eval_rays was) or with no error on either side."""
    pw, pn = _accuracy(wide), _accuracy(narrow)
    nw = wide.meta.get("report", {}).get("eval_rays")
    nn = narrow.meta.get("report", {}).get("eval_rays")
    if pw <= pn:
        return 0.0 if pw == pn else -math.inf
    var = (pw * (1 - pw) / nw + pn * (1 - pn) / nn) if nw and nn else 0.0
    return (pw - pn) / math.sqrt(var) if var > 0 else math.inf


def narrowest_proxy(mesh, config: ProxyConfig, widths, target: float, cache: ProxyCache,
                    train: bool, progress: bool, max_bytes: int | None = None):
    """Narrowest width whose proxy meets `target`; else, of those found (those lighter than
    max_bytes where any is: a heavier one would be replicated instead), the narrowest that
    the most accurate does not lead by more than Z_LEAD standard errors (`lead_z`).

    returns (proxy or None, tried {width: accuracy}, why-unavailable or None)
    """
    tried, found, unavailable = {}, {}, None
    for w in sorted(widths):
        cfg = config.with_width(w)
        proxy = cache.get(mesh, cfg)
        if proxy is None and train:
            try:
                proxy = cache.get_or_train(mesh, cfg, progress=progress)
            except ProxyUnavailable as e:
                unavailable = str(e)
                continue  # a wider proxy may still be cached
            except Exception as e:  # a failed training must not fail the render
                log.exception("training a width-%d proxy for %r failed", w, mesh.name)
                unavailable = f"training failed at width {w}: {e!r}"
                continue
        if proxy is None:
            continue
        tried[w], found[w] = _accuracy(proxy), proxy
        if tried[w] >= target:
            return proxy, tried, None
    if not found:
        return None, tried, unavailable or "no cached proxy and training is disabled"
    pool = [w for w in found if max_bytes is None or found[w].nbytes < max_bytes] or found
    best = _most_accurate(tried, pool)
    kept = min(w for w in pool if lead_z(found[best], found[w]) <= Z_LEAD)
    return found[kept], tried, None


def needs_training(mesh, config: ProxyConfig, widths, target: float, cache: ProxyCache) -> bool:
    """Whether `narrowest_proxy(..., train=True)` would train: some width, up to the
    narrowest cached one meeting `target`, is not cached. mesh: a Mesh or MeshMeta."""
    for w in sorted(widths):
        proxy = cache.get(mesh, config.with_width(w))
        if proxy is None:
            return True
        if _accuracy(proxy) >= target:
            return False
    return False


def plan_proxies(scene, partition, target_accuracy: float = 0.97, cache: ProxyCache | None = None,
                 train: bool = True, config: ProxyConfig | None = None,
                 widths: tuple[int, ...] = DEFAULT_WIDTHS, progress: bool = False,
                 trainer=None) -> ProxyPlan:
    """Decide, for every base mesh of `scene` split by `partition` (its shard_meshes: per
    shard, the mesh indices it holds), whether shards need a proxy of it, and get them.

    scene: a Scene, or a SceneMeta when `trainer` is given (or train is False): then no
    vertex array is read here. trainer(meshes: list[int], config, widths, target) fills
    the cache with the proxies of those meshes (nprt.proxies.tasks.RayTrainer: one Ray task per
    mesh, in parallel) and returns {mesh: why it failed} for those it could not train."""
    cache = cache or ProxyCache()
    config = config or ProxyConfig()
    k = len(partition.shard_meshes)
    holders = [0] * len(scene.meshes)
    for held in partition.shard_meshes:
        for m in set(held):
            holders[m] += 1
    used = set(np.unique(scene.instance_mesh).tolist())
    decisions, proxies, replicated = [], {}, set()
    smallest = estimate_proxy_bytes(config.with_width(min(widths)))
    failed: dict[int, str] = {}
    if train and trainer is not None:
        wanted = [i for i, m in enumerate(scene.meshes)
                  if i in used and holders[i] < k and m.nbytes >= smallest
                  and needs_training(m, config, widths, target_accuracy, cache)]
        if wanted:
            failed = trainer(wanted, config, widths, target_accuracy)
        train = False  # what could be trained is in the cache now
    for i, mesh in enumerate(scene.meshes):
        d = ProxyDecision(i, mesh.name, mesh.content_hash, "none", "", int(mesh.nbytes))
        decisions.append(d)
        if i not in used:
            d.reason = "no instances"
        elif holders[i] >= k:
            d.reason = "local to the only shard" if k == 1 else f"held by all {k} shards"
        elif mesh.nbytes < smallest:
            d.decision, d.proxy_bytes = "replicate", smallest
            d.reason = (f"mesh {mesh.nbytes} B < proxy estimate {smallest} B at width "
                        f"{min(widths)}: replicated exactly on every shard")
        else:
            proxy, d.tried, why = narrowest_proxy(mesh, config, widths, target_accuracy,
                                                  cache, train, progress, int(mesh.nbytes))
            why = failed.get(i, why)
            if proxy is None:
                d.decision, d.reason = "fallback", f"traced exactly: {why}"
            else:
                _choose(d, proxy, target_accuracy,
                        estimate_proxy_bytes(config.with_width(max(widths))))
        if d.decision == "replicate":
            replicated.add(i)
        elif d.decision == "proxy":
            proxies[i] = proxy
        log.info("mesh %d %r: %s (%s)", i, mesh.name, d.decision, d.reason)
    return ProxyPlan(decisions, proxies, replicated, target_accuracy)


def _choose(d: ProxyDecision, proxy: Proxy, target: float, budget: int) -> None:
    """Fill a `proxy` decision, or `replicate` when the mesh is the cheaper way to meet the
    target: the chosen proxy outweighs it, or no width met the target and the mesh is
    lighter than a proxy at the widest width tried (budget: its estimated bytes). An exact
    copy always meets the target, and it fits in what the policy was ready to ship."""
    d.width, d.accuracy = int(proxy.meta["width"]), _accuracy(proxy)
    d.proxy_bytes, d.train_s = proxy.nbytes, proxy.timing.get("train_s")
    best_w = _most_accurate(d.tried)
    if proxy.nbytes >= d.mesh_bytes:
        d.decision = "replicate"
        d.reason = (f"proxy at width {d.width} is {proxy.nbytes} B >= mesh {d.mesh_bytes} B: "
                    f"replicated exactly on every shard")
    elif d.accuracy >= target:
        d.decision = "proxy"
        d.reason = f"width {d.width} is the narrowest meeting accuracy {target:.3f}"
    elif d.mesh_bytes <= budget:
        d.decision = "replicate"
        d.reason = (f"no width met accuracy {target:.3f} (best {d.tried[best_w]:.4f} at width "
                    f"{best_w}), and the mesh ({d.mesh_bytes} B) is lighter than the widest "
                    f"proxy (about {budget} B): replicated exactly on every shard")
    else:
        d.decision = "proxy"
        d.reason = (f"no width met accuracy {target:.3f}; best held-out accuracy "
                    f"{d.tried[best_w]:.4f} at width {best_w}")
        if best_w != d.width:
            d.reason += (f"; width {d.width} ({d.accuracy:.4f}) chosen: no wider proxy lighter "
                         f"than the mesh leads it by more than {Z_LEAD:g} standard errors")
        d.reason += ("; kept: a job's accuracy target (one is set by default) picks its "
                     "confidence bands from its own held-out error curve, and the rays it is "
                     "unsure of are traced exactly")
    if proxy.meta.get("report", {}).get("capped"):
        d.reason += ("; its training hit the wall-clock safety cap before its step budget, "
                     "so it is not reproducible")
