"""Routing: where a ray goes next (exact forwarding, proxy prediction, the oracle)."""
