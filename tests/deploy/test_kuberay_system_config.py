"""The KubeRay heads start Ray with nprt's system config, as `ray up`'s head does
(tests/distributed/test_ray_calls.py): KubeRay pastes a rayStartParams value after
`--name=` into the head's shell command, so the value, read as the shell reads it, must be
the JSON of RAY_SYSTEM_CONFIG."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import yaml

from nprt.workers.runtime.raysession import RAY_SYSTEM_CONFIG

KUBERAY = Path(__file__).resolve().parents[2] / "deploy" / "kuberay"


def _heads() -> dict[str, dict]:
    heads = {}
    for path in sorted(KUBERAY.glob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            if doc["kind"] not in ("RayCluster", "RayJob"):  # a Service, ...
                continue
            spec = doc["spec"].get("rayClusterSpec", doc["spec"])
            heads[f"{path.name}:{doc['kind']}"] = spec["headGroupSpec"]["rayStartParams"]
    return heads


def test_every_kuberay_head_starts_ray_with_nprts_system_config():
    heads = _heads()
    assert len(heads) == 2
    for name, params in heads.items():
        words = shlex.split(f"--system-config={params['system-config']}")
        assert len(words) == 1, name
        assert json.loads(words[0].split("=", 1)[1]) == RAY_SYSTEM_CONFIG, name
