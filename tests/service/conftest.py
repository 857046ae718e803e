"""Fixtures: one live REST + gRPC server per module, an httpx client, a GLB scene."""

from __future__ import annotations

import httpx
import pytest

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
