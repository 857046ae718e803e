"""Proxy experiments that were measured and not adopted (smaller boxes, levers, thin shells)."""
