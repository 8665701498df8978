"""The Dask executor: batches to Dask workers, results back in submission order.

A batch (the unit the random stream is keyed by) is small and fixed by the spec, so the
result does not depend on how it runs; a Dask *task* evaluates a group of consecutive
batches, sized so a task is worth its round trip. The group size adapts to what the executor
has seen, which changes only how the work is cut, never a result:

- the compute time per batch, measured on the workers, caps a task at ``TASK_SECONDS``;
- the number of batches the previous population consumed estimates this one's need, so
  the tasks in flight at a population's start (two per worker) hold that many batches and
  a 20 % margin between them; past the estimate (or with none yet) the size grows with the
  batches consumed.

Tasks are submitted ahead (two per worker up to the expected need) so every worker stays
busy; the caller consumes results strictly in submission order (the oldest first, never
whichever finishes first: that would bias the posterior toward cheap parameters). When the
caller has enough and closes the iterator, the surplus tasks are cancelled. Each batch
carries its own seed, so a task Dask reruns after a worker died gives the same answer, and
the result does not depend on the number of workers.

The job's description and data go to the cluster once, as the task :func:`job_payload` that
every batch depends on. The scheduler keeps its inputs, so if every worker holding it dies
(or all workers are restarted) it is recomputed and the waiting batches go on.
"""

from __future__ import annotations

import itertools
import math
import uuid
from collections import deque
from collections.abc import Iterable, Iterator

import dask
from distributed import Client, Future, LocalCluster

from abcns.executor import Draw, Simulated, pack_draws
from worker.evaluate import evaluate_on_worker, job_payload

TASK_SECONDS = 0.1  # compute time a task aims at, at most (the round trip is a few ms)

#: Dask settings for abcns's workers: no statistical profiler (it samples every worker's
#: threads every 10 ms; with many workers per core it took a measurable share of the CPU).
#: ``local_cluster`` applies them; for stock workers, see docs/deploy.md.
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}


def local_cluster(n_workers: int, dashboard: bool = False) -> LocalCluster:
    """The embedded cluster: ``n_workers`` single-threaded worker processes on this machine."""
    with dask.config.set(WORKER_CONFIG):
        return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                            dashboard_address=":0" if dashboard else None)


class DaskExecutor:
    def __init__(self, client: Client, job_key: str, description: dict, arrays: dict, allow_import: bool = False):
        self.client = client
        self.job_key = job_key
        self.nonce = uuid.uuid4().hex[:8]  # keys unique to this run of the job
        self.payload: Future = client.submit(job_payload, description, arrays, allow_import,
                                             key=f"abcns-{job_key[:12]}-data-{self.nonce}", pure=False)
        self.expected: int | None = None  # batches the previous map call consumed
        self.batch_seconds: float | None = None  # compute time per batch on a worker (smoothed)

    def close(self) -> None:
        """Release the job's data on the cluster."""
        self.payload.release()

    def _n_workers(self) -> int:
        """One scheduler round trip per population."""
        return max(1, len(self.client.scheduler_info(n_workers=-1).get("workers", {})))

    def _need(self) -> int:
        """Batches this call is expected to consume: the previous call's count, 20 % more."""
        return math.ceil(1.2 * self.expected) if self.expected is not None else 1

    def _group_size(self, need: int, consumed: int, n_workers: int) -> int:
        """Batches in the next task, given the batches consumed so far in this call: the
        tasks in flight at the start cover the expected need between them; past that (or
        with no estimate yet) the size grows with what has been consumed."""
        size = math.ceil(max(need, consumed) / (2 * n_workers))
        if self.batch_seconds is not None and self.batch_seconds > 0:
            size = min(size, int(TASK_SECONDS / self.batch_seconds))
        return max(1, size)

    def map(self, draws: Iterable[Draw]) -> Iterator[Simulated]:
        pending: deque[tuple[Future, int]] = deque()  # (task, batches in it), oldest first
        it = iter(draws)
        exhausted = False
        n_workers = self._n_workers()
        need = self._need()
        consumed = submitted = 0
        try:
            while True:
                # up to the expected need, two tasks per worker in flight; past it, one, so
                # surplus work does not hold the workers when the population is full
                while not exhausted and len(pending) < (2 if submitted < need else 1) * n_workers:
                    group = list(itertools.islice(it, self._group_size(need, consumed, n_workers)))
                    if not group:
                        exhausted = True
                        break
                    key = (f"abcns-{self.job_key[:12]}-t{group[0].population}"
                           f"-b{group[0].index}-{group[-1].index}-{self.nonce}")
                    pending.append((self.client.submit(evaluate_on_worker, self.job_key, self.payload, pack_draws(group),
                                                       key=key, pure=False), len(group)))
                    submitted += len(group)
                if not pending:
                    return
                task, size = pending.popleft()
                evaluated, seconds = task.result()
                self.batch_seconds = seconds / size if self.batch_seconds is None else \
                    0.7 * self.batch_seconds + 0.3 * seconds / size
                for result in evaluated:
                    consumed += 1
                    yield result
        finally:
            self.expected = max(consumed, 1)
            if pending:
                self.client.cancel([task for task, _ in pending])
