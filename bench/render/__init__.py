"""Render benchmarks: reference, distributed, scale, extremes, frames, massive scenes, setup."""
