"""One local Ray for the whole directory (starting one takes seconds). The multi-node test
shuts it down to build its own cluster; `ray_local` brings it back for whatever runs next."""

from __future__ import annotations

import logging

import pytest
import ray

from scene.demos import make_demo
from tests.distributed.helpers import SCENES, SIZE, reference, settings

RAY_CPUS = 4


def start_local_ray() -> None:
    ray.init(num_cpus=RAY_CPUS, include_dashboard=False, log_to_driver=False,
             logging_level=logging.WARNING)


@pytest.fixture(scope="session")
def _ray_session():
    yield
    if ray.is_initialized():
        ray.shutdown()


@pytest.fixture(scope="module")
def ray_local(_ray_session):
    """The shared local Ray instance, started on first use (again after the cluster test)."""
    if not ray.is_initialized():
        start_local_ray()
    yield


@pytest.fixture(scope="session")
def scenes() -> dict:
    return {name: make_demo(name, SIZE) for name in SCENES}


@pytest.fixture(scope="session")
def references(scenes) -> dict:
    """Single-process reference renders of every demo at the default test settings."""
    return {name: reference(scene, settings(0)) for name, scene in scenes.items()}
