"""Proxy training benchmarks: accuracy against steps and width, determinism."""
