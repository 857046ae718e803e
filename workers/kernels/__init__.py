"""numba kernels: the top-level BVH, shading, the counter-based RNG, sampling, origin offsets."""
