"""The job state machine as the scheduler drives it: every change is a compare-and-set in
the store followed by a state event, so every API worker's watchers hear of it."""

from __future__ import annotations

import logging

from nprt.service.store import JobStore

log = logging.getLogger(__name__)


class JobStates:
    def __init__(self, store: JobStore):
        self.store = store

    def move(self, job_id: str, state: str, from_states: tuple[str, ...], **fields) -> bool:
        """Compare-and-set to a non-terminal state; watchers hear of it when it happened."""
        moved = self.store.transition(job_id, state, from_states, **fields)
        if moved:
            self.store.state_event(job_id)
        return moved

    def end(self, job_id: str, state: str, **fields) -> str | None:
        """Enter a terminal state unless the job has one already; returns the state it got
        (a stored cancel turns success into canceled)."""
        got = self.store.finish(job_id, state, **fields)
        if got is not None:
            self.store.state_event(job_id)
        return got

    def requeue(self, job_id: str, max_retries: int, exc: Exception) -> bool:
        """Send a job whose Ray node was lost back to the queue; it resumes from its
        checkpoint on fresh shards, at most max_retries times."""
        if not self.store.requeue(job_id, max_retries):
            return False
        rec = self.store.get(job_id)
        log.warning("job %s: lost its shards (%s); re-queued from pass %d, retry %d of %d",
                    job_id, exc, rec.passes_done, rec.retries, max_retries)
        self.store.state_event(job_id)
        return True
