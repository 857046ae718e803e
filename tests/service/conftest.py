"""Fixtures: one live REST + gRPC server per module, an httpx client, a GLB scene."""

from __future__ import annotations

import os

import httpx
import pytest

# Scheduler processes the tests start keep an autogroup of their own, as before SCHED_IDLE
# became the default: under pytest-xdist the other worker's in-process renders run in this
# session, and an idle-policy scheduler beside them would get almost no CPU.
# test_priority.py starts its services with the defaults and checks them.
os.environ.setdefault("NPRT_SCHEDULER_CPU", "batch")
os.environ.setdefault("NPRT_SCHEDULER_OWN_SESSION", "true")

from tests.service.helpers import LiveServer, settings_for, two_box_glb


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("service")
    with LiveServer(settings_for(tmp), grpc=True) as server:
        yield server


@pytest.fixture(scope="module")
def client(live):
    with httpx.Client(base_url=live.url, timeout=30.0) as c:
        yield c


@pytest.fixture(scope="module")
def glb_path(tmp_path_factory):
    return two_box_glb(tmp_path_factory.mktemp("glb") / "two_boxes.glb")
