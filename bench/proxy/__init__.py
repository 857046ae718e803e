"""Proxy quality benchmarks: proxy mode against exact and the oracle, bands, sweeps, confidence."""
