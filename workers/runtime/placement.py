"""Placement: which shard holds which meshes and instances, which meshes are replicated
and which get a proxy, decided from scene metadata alone (`nprt.scene.meta.SceneMeta`): the
driver reads no vertex array to plan, and each shard then loads its own meshes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nprt.scene.meta import SceneMeta
from nprt.scene.partition import Partition, partition
from nprt.workers.runtime.protocol import EVERYWHERE
from nprt.workers.settings import RenderSettings


def make_plan(scene, part, settings: RenderSettings, proxy_dir=None, train=True,
              trainer=None):
    """Which meshes get a proxy, are replicated, or need nothing (nprt.proxies.policy).
    scene: a Scene or SceneMeta; trainer: trains the missing proxies (for instance as
    parallel Ray tasks, nprt.proxies.tasks), else they are trained here one after another."""
    from nprt.proxies.cache import ProxyCache
    from nprt.proxies.policy import plan_proxies

    config, widths = _proxy_config(settings)
    return plan_proxies(scene, part, target_accuracy=settings.proxy.accuracy_target,
                        cache=ProxyCache(proxy_dir), train=train, config=config,
                        widths=widths, trainer=trainer)


def _proxy_config(settings: RenderSettings):
    """(ProxyConfig, widths tried) of a job's proxy knobs: one reading for the plan and
    for the replicate threshold."""
    from nprt.proxies.config import DEFAULT_WIDTHS, ProxyConfig

    knobs = settings.proxy
    return (ProxyConfig(steps=knobs.steps),
            DEFAULT_WIDTHS if knobs.width is None else (knobs.width,))


@dataclass(eq=False)
class Placement:
    """owner : (m,) int32 shard of each instance, or EVERYWHERE (replicated mesh);
    shard_meshes : per shard, the sorted mesh indices it loads (its own + replicated);
    proxies : mesh index -> Proxy (proxy mode)."""

    meta: SceneMeta
    partition: Partition
    owner: np.ndarray
    shard_meshes: list[tuple[int, ...]]
    plan: object = None
    proxies: dict = field(default_factory=dict)


def lighter_than_a_proxy(meta: SceneMeta, settings: RenderSettings) -> list[int]:
    """Instanced meshes lighter than the smallest proxy the policy would train (its
    `replicate` rule, nprt.proxies.policy): every mode copies them to every shard. A ground
    plane of 120 bytes held by one shard drew a third of all shard CPU in city at K = 8
    (bench_visits), every ray that fell on it forwarded there."""
    from nprt.proxies.config import estimate_proxy_bytes

    config, widths = _proxy_config(settings)
    smallest = estimate_proxy_bytes(config.with_width(min(widths)))
    used = set(np.unique(meta.instance_mesh).tolist())
    return [m for m, mesh in enumerate(meta.meshes) if m in used and mesh.nbytes < smallest]


def plan_placement(scene, settings: RenderSettings, proxy_dir=None,
                   trainer=None) -> Placement:
    """Plan K shards for `scene` (a Scene or SceneMeta) from its metadata; a Scene's meshes
    are read only to train the proxies it lacks when no trainer is given.

    The partition balances ray work over the meshes that are not copied to every shard.
    In proxy (and oracle) mode the plan may copy more meshes (its proxy outweighs it, or no
    width meets the accuracy target and it is lighter than the widest proxy:
    nprt.proxies.policy), and those may be all a shard was given: forest:small at
    K = 8 left five shards with no instance of their own, idle while the others worked.
    So the partition is made again with them copied, until the plan copies nothing new
    (the copied set only grows, so at most once per mesh; once in practice)."""
    meta = SceneMeta.of(scene)
    k = settings.shards
    copied = set(lighter_than_a_proxy(meta, settings)) if k > 1 else set()
    plan = None
    while True:
        part = partition(meta, k, replicated=sorted(copied), byte_slack=settings.byte_slack)
        if settings.mode not in ("proxy", "oracle"):
            break
        # The oracle bounds the proxy mode, so it gets the same placement: meshes
        # lighter than their proxy are replicated (it trains nothing to learn that).
        # The scene as given: a Scene's meshes are trained here when no trainer is given
        # (the metadata has no vertices); the pool passes metadata and a trainer.
        plan = _kept(plan, make_plan(scene, part, settings, proxy_dir,
                                     train=settings.mode == "proxy", trainer=trainer))
        if plan.replicated <= copied:
            break
        copied |= plan.replicated
    owner = np.asarray(part.instance_shard, np.int32).copy()
    held = [set(m) for m in part.shard_meshes]
    # A mesh to copy is copied only where the partition took it as such (it does not with
    # fewer instances of other meshes than shards), and wherever the plan says so.
    replicated = {m for m in copied if all(m in h for h in held)}
    proxies = {}
    if plan is not None:
        proxies = plan.proxies if settings.mode == "proxy" else {}
        replicated |= plan.replicated
    for m in sorted(replicated):  # cheaper to copy than to model, or to forward rays to
        owner[meta.instances_of_mesh(m)] = EVERYWHERE
        for h in held:
            h.add(m)
    return Placement(meta, part, owner, [tuple(sorted(h)) for h in held], plan, proxies)


def _kept(before, plan):
    """`plan`, keeping an earlier plan's `replicate` decisions: once copied to every shard,
    the partition gives those meshes to all of them, and a new plan would only say so
    ("held by all K shards"), not why they are copied."""
    if before is None:
        return plan
    from nprt.proxies.policy import ProxyPlan

    decisions = [b if b.decision == "replicate" else d
                 for b, d in zip(before.decisions, plan.decisions, strict=True)]
    return ProxyPlan(decisions, plan.proxies, before.replicated | plan.replicated,
                     plan.target_accuracy)
