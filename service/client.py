"""A small httpx client for the REST API, used by `nprt submit`, `nprt jobs` and the
benchmark."""

from __future__ import annotations

import json
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import httpx

RETRY_STATUSES = (429, 503)  # sent with Retry-After when the service is full or busy
MAX_RETRY_WAIT_S = 600.0  # a submission keeps retrying this long in all

_UPLOAD_TYPES = {".glb": "model/gltf-binary", ".gltf": "model/gltf+json",
                 ".zip": "application/zip", ".json": "application/json"}


class ApiError(RuntimeError):
    def __init__(self, response: httpx.Response):
        self.status_code = response.status_code
        try:  # RFC 9457 problem details; a 422's detail already names each field
            problem = response.json()
            detail = problem.get("detail") or problem.get("title")
        except (ValueError, AttributeError):
            detail = response.text
        super().__init__(f"{response.request.method} {response.request.url} -> "
                         f"{response.status_code}: {detail}")


class Client:
    def __init__(self, base_url: str, token: str | None = None, timeout_s: float = 30.0,
                 max_retry_wait_s: float = MAX_RETRY_WAIT_S):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout_s)
        self.max_retry_wait_s = max_retry_wait_s

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.http.close()

    def _ok(self, r: httpx.Response) -> httpx.Response:
        if r.is_error:
            raise ApiError(r)
        return r

    def upload_scene(self, path: Path) -> dict:
        with path.open("rb") as f:
            r = self.http.post("/v1/scenes", content=f, params={"filename": path.name},
                               headers={"Content-Type": _UPLOAD_TYPES.get(
                                   path.suffix.lower(), "application/octet-stream")})
        return self._ok(r).json()

    def submit(self, scene: str, settings: dict, idempotency_key: str | None = None) -> dict:
        """Submit a job. A 429 or 503 with Retry-After (the queue is full, the store busy)
        is retried after that many seconds, up to max_retry_wait_s in all, with one
        Idempotency-Key: however often it is sent, one job is made."""
        key = idempotency_key or uuid.uuid4().hex
        waited = 0.0
        while True:
            r = self.http.post("/v1/jobs", json={"scene": scene, **settings},
                               headers={"Idempotency-Key": key})
            after = _retry_after_s(r)
            if after is None or waited + after > self.max_retry_wait_s:
                return self._ok(r).json()
            print(f"the service answered {r.status_code}; retrying in {after:g} s",
                  file=sys.stderr)
            time.sleep(after)
            waited += after

    def job(self, job_id: str) -> dict:
        return self._ok(self.http.get(f"/v1/jobs/{job_id}")).json()

    def jobs(self, offset: int = 0, limit: int = 50, state: str | None = None) -> dict:
        """One page of jobs, newest first: {data, count, offset, limit}."""
        params = {"offset": offset, "limit": limit} | ({"state": state} if state else {})
        return self._ok(self.http.get("/v1/jobs", params=params)).json()

    def cancel(self, job_id: str) -> dict:
        return self._ok(self.http.post(f"/v1/jobs/{job_id}/cancel")).json()

    def delete(self, job_id: str) -> None:
        self._ok(self.http.delete(f"/v1/jobs/{job_id}"))

    def logs(self, job_id: str) -> str:
        """The job's log so far."""
        return self._ok(self.http.get(f"/v1/jobs/{job_id}/logs")).text

    def follow_logs(self, job_id: str) -> Iterator[str]:
        """Log lines as they are written, until the job ends."""
        for event, data in self._sse(f"/v1/jobs/{job_id}/logs", {"follow": 1}):
            if event == "log":
                yield data

    def image(self, job_id: str, fmt: str = "png") -> bytes:
        return self._ok(self.http.get(f"/v1/jobs/{job_id}/image.{fmt}")).content

    def frame(self, job_id: str, frame: int, fmt: str = "png") -> bytes:
        """One finished frame of a frames job."""
        return self._ok(self.http.get(f"/v1/jobs/{job_id}/frames/{frame}.{fmt}")).content

    def events(self, job_id: str) -> Iterator[tuple[str, str]]:
        """(event, data) pairs of the job's SSE stream until the server closes it."""
        return self._sse(f"/v1/jobs/{job_id}/events")

    def _sse(self, path: str, params: dict | None = None) -> Iterator[tuple[str, str]]:
        with self.http.stream("GET", path, params=params,
                              timeout=httpx.Timeout(self.http.timeout.connect, read=None)) as r:
            if r.is_error:
                r.read()
                raise ApiError(r)
            event, data = "message", []
            for line in r.iter_lines():
                if not line:
                    if data:
                        yield event, "\n".join(data)
                    event, data = "message", []
                elif line.startswith("event:"):
                    event = line[6:].strip()
                elif line.startswith("data:"):
                    data.append(line[5:].removeprefix(" "))

    def follow(self, job_id: str, progress: bool = True) -> dict:
        """Follow SSE with a tqdm bar (passes) until the job ends; returns the final job."""
        from tqdm import tqdm

        job = None
        with tqdm(total=None, unit="pass", disable=not progress, file=sys.stderr,
                  desc=job_id[:8]) as bar:
            for event, data in self.events(job_id):
                if event == "state":
                    job = json.loads(data)
                    bar.total = job["passes_total"]
                    bar.n = job["passes_done"]
                    bar.set_postfix_str(job["state"])
                elif event == "tile":
                    bar.n = json.loads(data)["pass_index"] + 1
                bar.refresh()
        return self.job(job_id) if job is None or job["state"] not in (
            "succeeded", "failed", "canceled") else job


def _retry_after_s(r: httpx.Response) -> float | None:
    """Seconds to wait before retrying r, when it is a 429 or 503 that says so."""
    if r.status_code not in RETRY_STATUSES:
        return None
    try:
        return max(0.0, float(r.headers["retry-after"]))
    except (KeyError, ValueError):  # no header, or an HTTP date: not a retry we can time
        return None
