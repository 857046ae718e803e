"""The wavefront inside a shard actor: batches, camera, integrator, lights, surfaces, the Shard."""
