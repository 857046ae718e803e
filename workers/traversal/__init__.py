"""Traversal: Embree geometry, the top-level instance boxes, local closest-hit and shadow tests."""
