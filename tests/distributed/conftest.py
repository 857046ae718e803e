"""One local Ray for the whole directory (starting one takes seconds). The multi-node test
runs last and shuts it down to build its own cluster; `ray_local` would bring it back."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import ray

from nprt.scene.demos import make_demo
from tests.distributed.helpers import SCENES, SIZE, reference, settings

RAY_CPUS = 4


def pytest_collection_modifyitems(items):
    """Run this directory's tests that build their own cluster last (a stable sort, and
    nothing outside this directory moves), so the shared Ray starts only once."""
    here = Path(__file__).parent

    def last(item) -> bool:
        return here in Path(item.path).parents and "cluster" in getattr(item, "fixturenames", ())

    items.sort(key=last)


def start_local_ray() -> None:
    ray.init(address="local", num_cpus=RAY_CPUS, include_dashboard=False, log_to_driver=False,
             logging_level=logging.WARNING)


@pytest.fixture(scope="package")
def _ray_session():
    """Ray is shut down when this directory is done, so later tests start from a clean slate."""
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
