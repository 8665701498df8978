"""The Dask executor: batches to Dask workers, results back in submission order.

Batches are submitted ahead (``in_flight``, default two per worker) so every worker stays
busy; the caller consumes results strictly in submission order (the oldest future first,
never whichever finishes first: that would bias the posterior toward cheap parameters).
When the caller has enough and closes the iterator, the surplus futures are cancelled.
Each batch carries its own seed, so a batch Dask reruns after a worker died gives the same
answer, and the result does not depend on the number of workers.

The job's description and data go to the cluster once, as the task :func:`job_payload` that
every batch depends on. The scheduler keeps its inputs, so if every worker holding it dies
(or all workers are restarted) it is recomputed and the waiting batches go on.
"""

from __future__ import annotations

import uuid
from collections import deque
from collections.abc import Iterable, Iterator

from distributed import Client, Future

from abcns.executor import Batch, Evaluated
from worker.evaluate import evaluate_on_worker, job_payload


class DaskExecutor:
    def __init__(self, client: Client, job_key: str, description: dict, arrays: dict,
                 allow_import: bool = False, in_flight: int | None = None):
        self.client = client
        self.job_key = job_key
        self.in_flight = in_flight
        self.nonce = uuid.uuid4().hex[:8]  # keys unique to this run of the job
        self.payload: Future = client.submit(job_payload, description, arrays, allow_import,
                                             key=f"abcns-{job_key[:12]}-data-{self.nonce}", pure=False)
        self.n_submitted = 0
        self.n_cancelled = 0

    def close(self) -> None:
        """Release the job's data on the cluster."""
        self.payload.release()

    def _depth(self) -> int:
        if self.in_flight is not None:
            return self.in_flight
        n_workers = len(self.client.scheduler_info(n_workers=-1).get("workers", {}))
        return max(2, 2 * n_workers)

    def map(self, batches: Iterable[Batch]) -> Iterator[Evaluated]:
        pending: deque[Future] = deque()
        it = iter(batches)
        exhausted = False
        depth = self._depth()  # one scheduler round trip per population, not per batch
        try:
            while True:
                while not exhausted and len(pending) < depth:
                    batch = next(it, None)
                    if batch is None:
                        exhausted = True
                        break
                    key = f"abcns-{self.job_key[:12]}-t{batch.population}-b{batch.index}-{self.nonce}"
                    pending.append(self.client.submit(evaluate_on_worker, self.job_key, self.payload, batch,
                                                      key=key, pure=False))
                    self.n_submitted += 1
                if not pending:
                    return
                yield pending.popleft().result()
        finally:
            if pending:
                self.n_cancelled += len(pending)
                self.client.cancel(list(pending))
