"""The shard-side code the driver starts without importing it.

`ShardActor` is what the pool starts as a Ray actor: it imports `nprt.workers.wavefront.shard`
(Embree, numba, ONNX Runtime) inside the actor's process and forwards each call to it.
`build_world` is a Ray task that builds the instance table, whose BVH is built by a
compiled kernel, on a worker: the driver keeps only the reference to it."""

from __future__ import annotations

import ray


class ShardActor:
    """Forwards to nprt.workers.wavefront.shard.Shard; tests/distributed/test_driver_imports.py
    checks that it has every public method of Shard."""

    def __init__(self, *args):
        from nprt.workers.wavefront.shard import Shard

        self._shard = Shard(*args)

    def __repr__(self) -> str:  # Ray prefixes the actor's log lines with it
        return repr(self.__dict__.get("_shard", "Shard(not started)"))

    def ready(self, *args):
        return self._shard.ready(*args)

    def warm(self, *args):
        return self._shard.warm(*args)

    def work(self, *args):
        return self._shard.work(*args)

    def collect(self, *args):
        return self._shard.collect(*args)

    def abort(self, *args):
        return self._shard.abort(*args)

    def set_world(self, *args):
        return self._shard.set_world(*args)

    def configure(self, *args):
        return self._shard.configure(*args)


@ray.remote(num_cpus=0)  # a moment's work: it must not wait for CPUs the shards reserve
def build_world(meta, owner):
    """nprt.workers.wavefront.world.ShardWorld.build(meta, owner), run on a worker."""
    from nprt.workers.wavefront.world import ShardWorld

    return ShardWorld.build(meta, owner)
