"""The deployment files: deploy/cluster.yaml against Ray's own schema and config checks,
copying no virtualenv, starting `nprt serve` with a token and a named log; the Dockerfile
and the KubeRay manifests agree with the package, the installed Ray and the CLI's flags."""

from __future__ import annotations

import fnmatch
import json
import re
import shlex
import tomllib
from pathlib import Path

import jsonschema
import pytest
import ray
import yaml

from nprt.service.cli import build_parser

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
REPO = DEPLOY.parent


@pytest.fixture(scope="module")
def cluster() -> dict:
    return yaml.safe_load((DEPLOY / "cluster.yaml").read_text())


@pytest.fixture(scope="module")
def kuberay() -> dict:
    docs = {}
    for path in sorted((DEPLOY / "kuberay").glob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            docs[doc["kind"]] = doc
    return docs


def test_cluster_yaml_passes_rays_schema_and_config_checks(cluster):
    schema = json.loads((Path(ray.__file__).parent / "autoscaler" / "ray-schema.json")
                        .read_text())
    jsonschema.validate(cluster, schema)
    from ray.autoscaler._private.util import prepare_config, validate_config

    validate_config(prepare_config(cluster))  # what `ray up` runs, defaults filled in


def test_schema_check_can_fail(cluster):
    schema = json.loads((Path(ray.__file__).parent / "autoscaler" / "ray-schema.json")
                        .read_text())
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**cluster, "max_workers": "three"}, schema)


def _rsync_excluded(path: str, patterns: list[str]) -> bool:
    """rsync --exclude for these simple patterns: one without '/' matches any path
    component; a leading '**/' matches at any depth."""
    parts = path.split("/")
    for pat in patterns:
        pat = pat.removeprefix("**/")
        if "/" not in pat and any(fnmatch.fnmatch(p, pat) for p in parts):
            return True
    return False


def test_cluster_yaml_copies_no_virtualenv_but_all_code(cluster):
    assert list(cluster["file_mounts"].values()) == ["."]  # the checkout, from its root
    excluded = cluster["rsync_exclude"]
    for venv_file in (".venv/bin/python", ".venv/lib/python3.11/site-packages/ray/__init__.py",
                      "sub/.venv/pyvenv.cfg", ".git/HEAD", "workers/__pycache__/x.pyc"):
        assert _rsync_excluded(venv_file, excluded), venv_file
    for code in ("workers/wavefront/shard.py", "deploy/bootstrap.sh", "proxies/shipped/a.nprx",
                 "pyproject.toml", "service/static/app.js"):
        assert not _rsync_excluded(code, excluded), code
    assert ".gitignore" in cluster["rsync_filter"]  # and whatever else it ignores
    assert ".venv/" in (REPO / ".gitignore").read_text().split()


def _serve_command(commands: list[str]) -> str:
    serve = [c for c in commands if "nprt serve" in c and not c.startswith("echo")]
    assert len(serve) == 1, commands
    return serve[0]


def _parse_nprt(command: str):
    """argv after the nprt executable, parsed by the real CLI (unknown flags fail)."""
    argv = shlex.split(command.split(">")[0])
    at = next(i for i, a in enumerate(argv) if a == "nprt" or a.endswith("bin/nprt"))
    return build_parser().parse_args(argv[at + 1:])


def test_cluster_yaml_serves_with_a_token_and_names_its_log(cluster):
    setup = " ".join(cluster["head_setup_commands"])
    assert "umask 077" in setup and "~/.nprt/api_token" in setup and "secrets" in setup
    commands = cluster["head_start_ray_commands"]
    serve = _serve_command(commands)
    assert 'NPRT_API_TOKEN="$(cat ~/.nprt/api_token)"' in serve
    log = re.search(r"> (\S+) 2>&1", serve).group(1)
    assert any(c.startswith("echo") and log in c for c in commands)  # says where its log is
    args = _parse_nprt(serve)
    assert (args.command, args.port, args.grpc_port) == ("serve", 8000, 50051)


def test_kuberay_manifests_match_the_image_ray_and_cli(kuberay):
    assert set(kuberay) == {"RayCluster", "RayJob", "Service"}
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    ray_version = re.search(r"ARG RAY_VERSION=(\S+)", dockerfile).group(1)
    assert ray_version == ray.__version__  # the image's Ray is the one tested here
    cluster, job = kuberay["RayCluster"]["spec"], kuberay["RayJob"]["spec"]
    for spec in (cluster, job["rayClusterSpec"]):
        assert spec["rayVersion"] == ray_version
        pods = [spec["headGroupSpec"]] + spec["workerGroupSpecs"]
        images = {c["image"] for p in pods for c in p["template"]["spec"]["containers"]}
        assert images == {"nprt:latest"}
    head = cluster["headGroupSpec"]["template"]["spec"]["containers"][0]
    token = next(e for e in head["env"] if e["name"] == "NPRT_API_TOKEN")
    assert "secretKeyRef" in token["valueFrom"] and "value" not in token  # never a literal
    serve = head["lifecycle"]["postStart"]["exec"]["command"][-1]
    assert "> /tmp/nprt-serve.log" in serve
    assert _parse_nprt(serve).command == "serve"
    render = _parse_nprt(job["entrypoint"])
    assert (render.command, render.ray_address) == ("render", "auto")


def test_dockerfile_copies_every_package_and_no_virtualenv():
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    copied = {line.split()[-2] for line in dockerfile.splitlines() if line.startswith("COPY")}
    assert "." not in copied  # never the whole context
    folders = tomllib.loads((REPO / "pyproject.toml").read_text())[
        "tool"]["setuptools"]["package-dir"].values()
    for folder in folders:
        assert folder in copied, folder
    ignore = (DEPLOY / "Dockerfile.dockerignore").read_text().split()
    assert "**/.venv" in ignore
