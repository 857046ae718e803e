"""K Shards of a placement in this one process, with no Ray: what benchmarks that step
shards in turn (bench/render/bench_visits.py) and tests of a shard's policy build."""

from __future__ import annotations

from nprt.workers.runtime.placement import plan_placement
from nprt.workers.runtime.protocol import ShardConfig
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.shard import Shard
from nprt.workers.wavefront.world import ShardWorld


def shards_in_process(scene, s: RenderSettings, warm: bool = True) -> list[Shard]:
    """The s.shards Shards of `s`'s placement of `scene` (a loaded Scene), begun for `s`;
    warm: their kernels compiled or loaded first."""
    placed = plan_placement(scene, s)
    world = ShardWorld.build(scene, placed.owner)
    shards = []
    for sid in range(s.shards):
        held = placed.shard_meshes[sid]
        proxies = {m: p for m, p in placed.proxies.items() if m not in held}
        sh = Shard(ShardConfig(sid, s.shards, s), world, {m: scene.meshes[m] for m in held},
                   proxies)
        if warm:
            sh.warm()
        sh.begin(s)
        shards.append(sh)
    return shards
