"""The Dask executor: batches to Dask workers, results back in submission order.

A batch (the unit the random stream is keyed by) is small and fixed by the spec, so the
result does not depend on how it runs; a Dask *task* evaluates a group of consecutive
batches. How the work is cut and how far ahead it runs adapt to what the executor has
seen, which changes only the cut, never a result:

- how many batches are submitted ahead follows the best estimate of the batches the
  caller still needs: ``abcns.filling``'s hints (``Stream.expect``: a lower bound when it
  opens a population, then an estimate from the acceptance so far after each batch), else
  the previous population's consumption, 10 % more; never more than two tasks per worker
  thread not yet completed (what the scheduler hands a worker: one to run, one next);
- a task's group is one batch until a batch's compute time has been measured, then about
  ``need / (2 x workers)`` batches, kept between ``MIN_TASK_SECONDS`` and
  ``MAX_TASK_SECONDS`` of compute time, so a cheap batch does not pay a round trip each
  and a dear one does not hold a worker long past the population's end; the floor never
  exceeds ``need / workers`` batches, so a cheap population still goes to every worker
  (one task each).

Tasks go to the scheduler in bulk (one ``client.map``, one scheduler message, for all the
tasks a hint asks for) and are queued there: a run's tasks form one task group that the
scheduler treats as "root-ish" (see the anchors in :class:`DaskExecutor`), so it hands them
to workers oldest first as threads free up (each ``client.map`` a new priority generation:
``fifo_timeout=0``). The oldest batch thus runs first, on whichever worker is free, and a
surplus task released before its turn never runs. Results are gathered as they complete
(``as_completed``, on the client's event loop) and handed to the caller strictly in
submission order (never whichever finishes first: that would bias the posterior toward
cheap parameters). Each batch carries its own seed, so a task Dask reruns after a worker
died gives the same answer, and the result does not depend on the number of workers.

A population cheap enough that the cluster would shorten it by less than Dask's round trips
cost (:data:`LOCAL_POPULATION_S`) is evaluated in the runner's process with the job's own
evaluator (:meth:`Stream.here`): on §4.1's kernel (~5 ms of simulations a population) a
cluster ran at half the speed of no cluster. Where a batch runs changes no result.

The job's budget reaches into a running batch. A stream waiting for a task's result asks
the run's :class:`abcns.filling.Budget` every ``WATCH_S`` whether the run must stop (its
time budget spent, or cancelled); if so it releases every task not yet consumed (a queued
one never runs; one already running finishes on its worker and is dropped) and raises
``Stopped``, so the run ends within ``WATCH_S`` instead of when the batch ends. A task's
group of batches is also capped by the remaining time: no more batches than the measured
compute time per batch fits into the seconds left (one batch at least: a batch is the unit
of the random stream and is never split). A result used is never affected: a stop by time
or cancel ends the run at the population being filled, whose batches are dropped.

The job's description and data go to the cluster once, as the task :func:`job_payload` that
every batch depends on (the tasks are in :mod:`worker.tasks`). The scheduler keeps its inputs, so if every worker holding it dies
(or all workers are restarted) it is recomputed and the waiting batches go on.
"""

from __future__ import annotations

import itertools
import math
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import cast

import dask
from distributed import Client, Future, LocalCluster, as_completed

from abcns.executor import Draw, Evaluate, Simulated, pack_draws, run_draw, unpack_results
from abcns.filling import Budget
from abcns.settings import Stopped
from worker.description import JobDescription
from worker.tasks import anchor, evaluate_on_worker, job_payload

#: compute time of a task, at least (a task costs ~1-2 ms of CPU in the client, scheduler and
#: worker together) and at most (a worker busy with a surplus task starts the next population late)
MIN_TASK_SECONDS = 0.02
MAX_TASK_SECONDS = 0.1
#: the expected need of a population, over the previous population's
NEED_MARGIN = 1.1
#: tasks not yet completed, at most, per worker thread: the scheduler gives a worker one to
#: run and one to start next; more would only wait in its queue, each costing the client and
#: the scheduler ~1-2 ms of CPU to submit and to release when the population ends first
IN_FLIGHT_PER_THREAD = 2
#: seconds, at most, that the client holds a message to the scheduler to send it with the next
#: (Dask's client: 10 ms). A population's first tasks follow the release of the last one's
#: surplus by the step's few milliseconds, and waited out the rest of the 10: with 1 ms, the
#: first task of a population started 6 ms after ``client.map`` instead of 10 (4 workers here)
CLIENT_BATCH_S = 0.001
#: the result of a task taken without ``as_completed`` (``Stream._next_completed``)
_UNTRACKED = object()

#: what Dask's round trips cost a population, in seconds of waiting (§4.1 on 2 cores: ~45 ms
#: a population through one worker against ~17 in the runner alone): a population whose
#: simulations the cluster would shorten by less than this is evaluated in the runner's
#: process (:meth:`Stream.here`). ``ABCNS_LOCAL_POPULATION_S`` (service.run.runner) sets it;
#: 0 keeps every population on the cluster
LOCAL_POPULATION_S = 0.025

#: seconds between two looks at the run's budget (time, cancel) while a stream waits for a
#: task: a stop takes effect within this even while a batch runs
WATCH_S = 0.1

#: Dask settings for abcns's clusters. ``local_cluster`` applies them; stock workers take them
#: from the environment (docs/deploy.md). Measured idle on this project's 2-core machine with
#: 32 worker processes: 66 % of a core with Dask's defaults, 11 % with these.
#: - no statistical profiler (it samples every worker's threads every 10 ms);
#: - the event-loop health tick every 500 ms, not 20 ms (it only warns of a blocked loop);
#: - the nanny's memory check every second, not 100 ms; the system monitor (dashboard
#:   figures) every 2 s, not 500 ms.
CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "500ms",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
}


def cluster_env() -> dict[str, str]:
    """:data:`CLUSTER_CONFIG` as the environment variables a stock ``dask scheduler`` / ``dask
    worker`` reads (docs/deploy.md, docker/compose.yaml)."""
    return {"DASK_" + key.upper().replace(".", "__").replace("-", "_"): str(value)
            for key, value in CLUSTER_CONFIG.items()}


def local_cluster(n_workers: int, dashboard: bool = False) -> LocalCluster:
    """The embedded cluster: ``n_workers`` single-threaded worker processes on this machine.

    It never asks for a fixed port: the scheduler listens on a free port, and so does its
    HTTP server, which Dask starts even without a dashboard (left unset, its address would
    be Dask's default port, which a user's own Dask dashboard often holds). With
    ``dashboard`` the dashboard is served there, on every interface; without, the HTTP
    server is on 127.0.0.1 with no dashboard."""
    with dask.config.set(CLUSTER_CONFIG):
        return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, scheduler_port=0,
                            dashboard_address=":0" if dashboard else "127.0.0.1:0",
                            scheduler_kwargs={"dashboard": dashboard})


class DaskExecutor:
    """Batches on the cluster's workers; with ``evaluate`` (the job's evaluator in this
    process) and ``local_s`` > 0 (what Dask's round trips cost a population), a population
    too cheap for the cluster to shorten by more than that is evaluated here instead
    (:meth:`Stream.here`): the same results, since a batch's result does not depend on where
    it runs. Never while other runs share this process (``alone`` says): their populations
    would take turns on one core while the workers wait."""

    def __init__(self, client: Client, job_key: str, description: JobDescription, arrays: dict, allow_import: bool = False,
                 budget: Budget | None = None, evaluate: Evaluate | None = None, local_s: float = 0.0,
                 alone: Callable[[], bool] = lambda: True):
        self.client = client
        # evaluating here: the job's evaluator, what Dask's round trips cost a population, and
        # whether this run is alone in its process (asked as each population opens)
        self.evaluate, self.local_s, self.alone = evaluate, local_s, alone
        comm = getattr(client, "scheduler_comm", None)  # the client's batched stream to the scheduler
        if comm is not None and getattr(comm, "interval", 0) > CLIENT_BATCH_S:
            comm.interval = CLIENT_BATCH_S
        self.budget = budget  # watched while a stream waits for a task; caps a task's expected time
        self.job_key = job_key
        self.nonce = uuid.uuid4().hex[:8]  # keys unique to this run of the job
        self._threads: tuple[float, int] | None = None  # (when asked, worker threads)
        # the batches' tasks form one task group per run, ``(name, population, first, last)``.
        # Its first tasks are anchors (no-ops), held until the executor closes, so the group (and
        # its count of tasks) outlives each population. Dask's scheduler queues the tasks of a
        # large group with few dependencies ("root-ish": more tasks than twice the worker
        # threads) and hands them out in priority order as threads free up. Without the anchors
        # the first population's tasks would be too few to count as root-ish, and the scheduler
        # would place them eagerly, most on the worker holding the job's data, one after
        # another; and a group the scheduler forgets when its last task is released would
        # start each population from zero.
        self.group = f"abcns-{job_key[:12]}-{self.nonce}"
        self.payload: Future = client.submit(job_payload, description, arrays, allow_import,
                                             key=(f"abcns-data-{job_key[:12]}-{self.nonce}",), pure=False)
        anchors = 2 * self.n_workers() + 1
        self.anchors: list[Future] = client.map(anchor, range(anchors), key=[(self.group, 0, 0, i) for i in range(anchors)],
                                                pure=False)
        self.expected: int | None = None  # batches the previous map call consumed
        self.batch_seconds: float | None = None  # compute time per batch on a worker (smoothed)
        # the compute time on the workers of every task consumed since the executor opened:
        # the useful work, for the efficiency a user sees (runner.Progress)
        self.busy_s = 0.0
        self.last_here = False  # the last stream closed was evaluated in this process (Stream.here)

    def close(self) -> None:
        """Release the job's data on the cluster."""
        self.payload.release()
        for future in self.anchors:
            future.release()

    def n_workers(self) -> int:
        """Worker threads in the cluster: asked of the scheduler at most once a second (a
        round trip took 30-60 ms on a loaded machine, once per population)."""
        now = time.monotonic()
        if self._threads is None or now - self._threads[0] > 1.0:
            self._threads = (now, max(1, sum(self.client.nthreads().values())))
        return self._threads[1]

    def group_size(self, need: int, consumed: int, n_workers: int, max_task_s: float = MAX_TASK_SECONDS) -> int:
        """Batches in the next task, given the batches expected and those consumed so far;
        one until a batch's compute time has been measured (a job's first tasks measure it),
        and no more than fit into the run's seconds left (:meth:`time_cap`) or into
        ``max_task_s`` of compute time."""
        if self.batch_seconds is None:
            return 1
        need = max(need, consumed)
        size = math.ceil(need / (2 * n_workers))
        if self.batch_seconds > 0:
            most = max(1, int(max_task_s / self.batch_seconds))
            # the floor of a task's compute time, but never so large that fewer tasks than
            # workers cover the need: a cheap population is shared by every worker, each its
            # part in one task (a floor of 20 ms made one task of a whole population, and a
            # surplus, on a kernel of ~1 ms a batch: a second worker had nothing to do)
            least = min(most, math.ceil(MIN_TASK_SECONDS / self.batch_seconds), math.ceil(need / n_workers))
            size = min(max(size, least), most, self.time_cap())
        return max(1, size)

    def time_cap(self) -> int:
        """Batches whose measured compute time fits into the run's seconds left (at least
        one: a batch is never split); unbounded without a time budget or a measurement."""
        left = self.budget.seconds_left() if self.budget is not None else None
        if left is None or not self.batch_seconds:
            return 2**62
        return max(1, int(left / self.batch_seconds))

    def map(self, draws: Iterable[Draw]) -> Stream:
        return Stream(self, iter(draws))

    def _measured(self, seconds: float, size: int, on_worker: bool = True) -> None:
        if on_worker:
            self.busy_s += seconds
        per = seconds / size
        self.batch_seconds = per if self.batch_seconds is None else 0.7 * self.batch_seconds + 0.3 * per


class Stream:
    """One call of :meth:`DaskExecutor.map`: an iterator of :class:`Simulated` in submission
    order; ``close()`` cancels the rest.

    How many batches are submitted ahead (tasks queue on the scheduler, oldest first) follows
    the best estimate of the batches still needed: at first the previous call's consumption,
    10 % more (with none, twice the caller's lower bound, or a task per worker), then the
    caller's estimate from the acceptance so far (``expect``: ``abcns.filling`` gives a lower
    bound when it opens a population and an estimate after each batch); at most
    ``IN_FLIGHT_PER_THREAD`` tasks per worker thread are in flight (not yet completed)."""

    def __init__(self, executor: DaskExecutor, draws: Iterator[Draw]):
        self.ex = executor
        self.draws = draws
        self.exhausted = False
        self.n_workers = executor.n_workers()
        # the previous call's consumption, 10 % more: the first estimate of the need
        self.need = math.ceil(NEED_MARGIN * executor.expected) if executor.expected is not None else None
        self.left = self.need  # batches still needed beyond those consumed (None: unknown)
        self.consumed = self.submitted = 0
        self.pending: deque[tuple[Future, int]] = deque()  # (task, batches in it), oldest first
        self.done: dict = {}  # results gathered, by task key, until their turn
        self.completed = as_completed(with_results=True, raise_errors=False)
        self.ready: deque[Simulated] = deque()  # the oldest task's results, not yet handed out
        self.closed = False
        self.local: bool | None = None  # evaluated in this process (:meth:`here`), decided at the first top-up

    def __iter__(self) -> Stream:
        return self

    def expect(self, batches: float, at_least: bool = False) -> None:
        """The caller expects to consume about ``batches`` more; tasks for that many, 10 % more,
        are submitted now. With ``at_least`` (a lower bound, when a population opens): the
        previous population's need (its consumption, 10 % more) when that is larger, else
        twice the bound or a task per worker, whichever is larger."""
        if at_least and self.consumed == 0:
            # the previous call's need, if known (never below the bound); else twice the bound
            least = math.ceil(batches)
            self.left = max(least, self.need) if self.need is not None else max(2 * least, self.n_workers)
        else:
            self.left = math.ceil(NEED_MARGIN * batches)
        if not self.closed:
            self._top_up()

    def _in_flight(self) -> int:
        """Tasks submitted and not yet completed."""
        return len(self.pending) - len(self.done)

    def here(self) -> bool:
        """Whether this population is evaluated in this process, not on the cluster: its
        simulations are cheap. Their cost ``c`` is a batch's compute time as last measured
        times the previous population's need; spread over W workers the cluster would save
        ``c (1 - 1/W)`` of it and pay the executor's ``local_s`` in round trips, so the
        population stays here when ``c <= local_s W / (W - 1)``, and never when ``c`` exceeds
        ``2 local_s`` (one worker too: the runner's process is no place for dear
        simulations), nor while other runs share this process. Decided once, before anything
        is submitted; the first population (nothing measured yet) goes to the cluster. Where a
        batch runs changes no result."""
        if self.local is None:
            ex, w = self.ex, self.n_workers
            cost = None if ex.batch_seconds is None or ex.expected is None else ex.expected * ex.batch_seconds
            spread = 2.0 if w < 2 else min(2.0, w / (w - 1))
            self.local = (ex.evaluate is not None and ex.local_s > 0 and cost is not None
                          and cost <= ex.local_s * spread and ex.alone())
        return self.local

    def _evaluate_here(self) -> Simulated | None:
        """The next draw, evaluated in this process (None: no draws left)."""
        draw = next(self.draws, None)
        if draw is None:
            self.exhausted = True
            return None
        start = time.perf_counter()
        result = run_draw(cast("Evaluate", self.ex.evaluate), draw)  # here() says it is set
        self.ex._measured(time.perf_counter() - start, 1, on_worker=False)
        self.submitted += 1
        return result

    def _top_up(self) -> None:
        """Submit tasks in one scheduler message until the estimate of the batches still
        needed is covered, or ``IN_FLIGHT_PER_THREAD`` tasks per worker thread are in
        flight; at least one task is (none for a population evaluated :meth:`here`)."""
        if self.here():
            return
        groups: list[list[Draw]] = []
        want = max(self.left or 1, 1)
        room = IN_FLIGHT_PER_THREAD * self.n_workers - self._in_flight()
        while not self.exhausted and ((self.submitted - self.consumed < want and len(groups) < room)
                                      or len(self.pending) + len(groups) == 0):
            group = list(itertools.islice(self.draws, self.ex.group_size(want, self.consumed, self.n_workers)))
            if not group:
                self.exhausted = True
                break
            groups.append(group)
            self.submitted += len(group)
        if not groups:
            return
        keys = [(self.ex.group, g[0].population, g[0].index, g[-1].index) for g in groups]
        n = len(groups)
        # fifo_timeout=0: each call is a new "generation" of the scheduler's priorities, so its
        # tasks come after every earlier call's (by default calls within 100 ms share one, and
        # each call's first task would jump ahead of the previous call's later ones). Client.map
        # types fifo_timeout str, but passes it on to the scheduler, which parses a number too
        # (Scheduler._set_priorities: int | float | str, through dask.utils.parse_timedelta)
        tasks = self.ex.client.map(evaluate_on_worker, [self.ex.job_key] * n, [self.ex.payload] * n,
                                   [pack_draws(g) for g in groups], key=keys, pure=False,
                                   fifo_timeout=0)  # type: ignore[arg-type]
        self.pending.extend(zip(tasks, map(len, groups), strict=True))
        self.completed.update(tasks)

    def _oldest(self) -> tuple[bytes, float]:
        """The oldest task's result, waiting for it (later ones are gathered meanwhile; when
        fewer tasks than worker threads are left in flight, more are submitted)."""
        task, _ = self.pending[0]
        while task.key not in self.done:
            future, result = self._next_completed(task)
            if future.key in self.done or not any(f.key == future.key for f, _ in self.pending):
                continue  # reported again after it was taken without ``as_completed``: already used
            self.done[future.key] = result
            if self._in_flight() < self.n_workers:
                self._top_up()
        result = self.done.pop(task.key)
        if task.status == "finished" and result is not _UNTRACKED:
            return result
        # an error or a cancellation (raises what ``result()`` raises), or a task whose result
        # ``as_completed`` never delivered
        return task.result()

    def _next_completed(self, oldest: Future) -> tuple[Future, object]:
        """The next task to complete and its result, waiting for it. While it waits, the
        run's budget is asked every ``WATCH_S`` whether the run must stop (time spent, or
        cancelled); then every task is released and ``Stopped`` raised: the run ends now,
        not when the running batch ends. ``oldest`` (the task the caller waits for) is
        looked at too: ``as_completed`` loses a task when the scheduler's connection drops
        while it fetches the result (its tracker dies on the closed comm), and the stream
        would wait for it forever; a task done but not delivered comes back as
        ``(oldest, _UNTRACKED)``, and its ``result()`` says what became of it."""
        budget = self.ex.budget
        while not self.completed.has_ready():
            reason = budget.reason() if budget is not None else None
            if reason is not None:
                self.close()
                raise Stopped(reason)
            if oldest.done():  # finished, erred or cancelled, and as_completed has not said so
                self._wait_for_a_result()  # its report may be on the way
                if not self.completed.has_ready():
                    return oldest, _UNTRACKED
            self._wait_for_a_result()
        return next(self.completed)

    def _wait_for_a_result(self) -> None:
        """Wait until a task completes, ``WATCH_S`` at most. ``as_completed`` queues a result,
        then notifies its condition; the queue is looked at with the condition held, so a
        result queued just before the wait is seen and one queued during it wakes it. (Looked
        at before the condition was taken, as ``as_completed.__next__`` does, a result that
        came in between went unnoticed until the timeout: 100 ms lost at the end of about one
        population in four, the workers idle.)"""
        condition = self.completed.thread_condition
        with condition:
            if not self.completed.has_ready():
                condition.wait(timeout=WATCH_S)

    def __next__(self) -> Simulated:
        if self.closed:
            raise StopIteration
        while not self.ready:
            self._top_up()
            if not self.pending:
                result = self._evaluate_here() if self.here() and not self.exhausted else None
                if result is None:
                    raise StopIteration
                self.ready.append(result)
                break
            packed, seconds = self._oldest()
            _, size = self.pending.popleft()
            self.ex._measured(seconds, size)
            self.ready.extend(unpack_results(packed))
        self.consumed += 1
        return self.ready.popleft()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.ex.expected = max(self.consumed, 1)
        self.ex.last_here = bool(self.local)
        # releasing a task the caller no longer needs cancels it (the scheduler forgets a
        # queued task nobody wants; one already running finishes and is dropped); unlike
        # ``client.cancel`` it does not wait for the scheduler's answer
        for task, _ in self.pending:
            task.release()
        self.pending.clear()
        self.done.clear()
        self.completed.clear()

    def __del__(self) -> None:  # a stream dropped without close() still frees the cluster
        try:
            self.close()
        except Exception:  # noqa: S110 - a destructor must not raise, and has no one to tell
            pass
