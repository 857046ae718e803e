"""A local Ray for the trace test, shut down when the module is done (the cluster tests
join their own cluster instead)."""

from __future__ import annotations

import logging

import pytest
import ray


@pytest.fixture(scope="module")
def ray_local():
    if ray.is_initialized():
        ray.shutdown()
    ray.init(address="local", num_cpus=3, include_dashboard=False, log_to_driver=False,
             logging_level=logging.WARNING)
    yield
    ray.shutdown()
