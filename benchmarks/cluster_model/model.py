"""The discrete-event model: a trace's populations replayed on W virtual Dask workers.

What is modelled (each piece is the code it stands for, its costs in :class:`Costs`):

- **The runner's process** (:class:`_Process`): one CPU and one event-loop thread. The main
  thread (the filling loop of ``abcns.filling``, the executor's top-ups and releases of
  ``service.run.dask_executor``, the population step) computes in 1 ms pieces; the event
  loop's callbacks (the client's gather per completed task and, for a LocalCluster, the
  scheduler's work) run one at a time and each waits for the GIL while the main thread
  computes, up to the switch interval (CPython's convoy effect); the store's writer
  (``service.run.runner.PopulationWriter``: appends coalesced, one a second at most) takes
  turns as I/O-bound Python.
- **The scheduler** (in the runner's process, or its own): tasks queued in priority order
  (today: submission order), each single-threaded worker given at most two at a time
  (Dask's ``worker-saturation`` 1.1), CPU per ``client.map`` call and per task taken,
  finished and released.
- **Dask's batched streams** (:class:`_Channel`): a message waits for its stream's interval
  since the last batch, then :attr:`Costs.latency`.
- **W single-threaded workers**: a task's batches run back to back (sleep per simulation,
  the trace's evaluator CPU, the codec), plus a per-task overhead; a released task that
  has not started never runs, one that has finishes and is dropped (surplus).
- **Today's executor policies**, ported from ``Stream`` (``_top_up``, ``expect``,
  ``_oldest``, ``close``; ``DaskExecutor.group_size`` and ``_measured`` called as they are):
  batches grouped into tasks by measured cost, the queue depth from the hints with 10 %
  margin, two tasks per worker thread in flight, results consumed in submission order,
  surplus released when the population is full, the 2 W + 2 held no-op tasks, the step on
  the main thread, the next population opened before the geometry, the run's start and end.
- **Designs** (:class:`Design`): issue O's look-ahead (while population t fills, ``L``
  batches of t + 1 drawn from t's bounds run at a lower priority than t's own; t + 1
  consumes them first, each yielding the trace's measured share of accepted rows, then its
  regular batches), carry-over (t + 1 first consumes t's next batches), tasks of k batches,
  the step's CPU, the scheduler's process, the top-up threshold.

Efficiency is the trace's simulations (what today's algorithm uses) x the simulation
time over (W x wall), the ``benchmarks.scale`` figure; so a design that wastes simulations
is charged for them in wall time.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import deque
from collections.abc import Callable, Generator
from dataclasses import dataclass, field

import numpy as np
import simpy

from benchmarks.cluster_model.costs import Costs
from benchmarks.cluster_model.trace import PopulationTrace, Trace
from service.run.dask_executor import IN_FLIGHT_PER_THREAD, MAX_TASK_SECONDS, NEED_MARGIN, DaskExecutor

#: Dask's worker-saturation 1.1 on a single-threaded worker: ceil(1.1 x 1) tasks at a time
WORKER_SLOTS = 2
#: the runner's store writer coalesces appends closer than this (ABCNS_STORE_INTERVAL_S default)
WRITE_INTERVAL_S = 1.0
#: the executor asks the scheduler for the worker count at most this often
NTHREADS_INTERVAL_S = 1.0
#: from a population's message with the job's turn over to the release of its loop's task: the
#: service's job thread looks every 0.2 s (``JobManager._on_worker``), half of it on average
TURN_RELEASE_S = 0.1

Proc = Generator[simpy.Event, object, object]


@dataclass(frozen=True)
class Design:
    """The executor and algorithm design being modelled (the defaults: today's).

    ``lookahead_batches`` / ``lookahead_share``: look-ahead batches of population t + 1 run
    while t fills, a fixed number, or a share of t + 1's expected batches (its new particles
    over the batch size and the last finished population's acceptance); 0: none (today).
    ``carry_batches`` / ``carry_share``: instead, population t + 1 first consumes population
    t's next batches after its last consumed one, that many (drawn from t's bounds too: t's
    surplus, put to use), which t's executor runs ahead as part of its own stream.
    ``task_batches``: batches per task (None: today's adaptive size). ``step_s``: the step's
    CPU (finish + geometry, in the trace's proportions; None: the trace's, scaled).
    ``scheduler``: "runner" (a LocalCluster: the scheduler shares the runner's process) or
    "own" (a remote cluster). ``refill``: while the executor waits for the oldest task, it
    tops up when fewer than ``refill x W`` tasks are in flight (today 1: a worker's second
    slot may empty first; 2: every completion refills)."""

    lookahead_batches: int = 0
    lookahead_share: float = 0.0
    carry_batches: int = 0
    carry_share: float = 0.0
    task_batches: int | None = None
    step_s: float | None = None
    scheduler: str = "runner"
    refill: float = 1.0

    def label(self) -> str:
        la = (f"L={self.lookahead_batches}" if self.lookahead_batches else
              f"L={self.lookahead_share:g}x" if self.lookahead_share else
              f"carry={self.carry_batches}" if self.carry_batches else
              f"carry={self.carry_share:g}x" if self.carry_share else "L=0")
        k = "k=auto" if self.task_batches is None else f"k={self.task_batches}"
        step = "step=trace" if self.step_s is None else f"step={1e3 * self.step_s:g}ms"
        refill = "" if self.refill == 1.0 else f" refill={self.refill:g}W"
        return f"{la} {k} {step} sched={self.scheduler}{refill}"


@dataclass
class Outcome:
    """What a replay gives: wall, efficiency, and where the workers' time went (seconds,
    summed over workers)."""

    workers: int
    wall: float
    efficiency: float
    simulations: int  # the trace's: what today's algorithm uses
    executed: int  # rows the workers simulated
    counted: int  # rows the run counts (today: the trace's; look-ahead: its rows too)
    time: dict[str, float] = field(default_factory=dict)
    runner_busy: float = 0.0  # the runner process's CPU, seconds
    scheduler_busy: float = 0.0
    steady: float = math.nan  # efficiency from population 1's record to the last's (benchmarks.scale's "steady")

    def shares(self) -> dict[str, float]:
        total = self.workers * self.wall
        return {k: v / total for k, v in self.time.items()}


class _Process:
    """A process's CPU. ``cpu``: a CPU-bound thread's work (the runner's main thread), in
    1 ms pieces; ``slices``: I/O-bound Python (zarr's writes); ``loop``: one callback of the
    process's one event-loop thread, run between two I/O waits. With ``gil``, CPython's GIL
    between them: a callback that finds the main thread computing waits until it stops or
    for the switch interval (``quantum``), then gets the GIL and gives it back at its next
    I/O wait (the "convoy effect", bpo-7946), so an event loop that needs n callbacks while
    the main thread computes waits up to n x 5 ms. Without it (a scheduler's own process)
    work is served in arrival order."""

    CHUNK = 0.001  # a CPU-bound thread's work is cut in 1 ms pieces so a waiting callback gets in on time

    def __init__(self, env: simpy.Environment, quantum: float, gil: bool):
        self.env, self.quantum, self.gil = env, quantum, gil
        self.res = simpy.PriorityResource(env, 1)
        self.loop_thread = simpy.Resource(env, 1)
        self.cpu_bound = 0  # CPU-bound threads running or waiting
        self.burst_end = 0.0  # when the computing threads' current work ends
        self.busy = 0.0

    def cpu(self, seconds: float) -> Proc:
        self.cpu_bound += 1
        try:
            while seconds > 1e-12:
                with self.res.request(priority=1) as req:
                    yield req
                    self.burst_end = max(self.burst_end, self.env.now + seconds)
                    q = min(seconds, self.CHUNK if self.gil else self.quantum)
                    yield self.env.timeout(q)
                    seconds -= q
                    self.busy += q
        finally:
            self.cpu_bound -= 1

    def slices(self, seconds: float, piece: float = 0.001) -> Proc:
        """I/O-bound Python work (zarr's own event loop and I/O threads): pieces that take turns
        with the CPU-bound threads, without holding the GIL against the event loop's callbacks."""
        while seconds > 1e-12:
            with self.res.request(priority=1) as req:
                yield req
                q = min(seconds, piece)
                yield self.env.timeout(q)
                seconds -= q
                self.busy += q

    def loop(self, seconds: float) -> Proc:
        """One callback of the process's event loop (one thread: callbacks run one at a time)."""
        with self.loop_thread.request() as turn:
            yield turn
            if self.gil and self.cpu_bound:
                # the GIL comes when the computing thread gives it up (its burst ends) or, at the
                # latest, one switch interval after the request (the holder is made to drop it)
                wait = min(self.quantum, self.burst_end - self.env.now)
                if wait > 0:
                    yield self.env.timeout(wait)
            with self.res.request(priority=0) as req:
                yield req
                if seconds > 0:
                    yield self.env.timeout(seconds)
                    self.busy += seconds


class _Channel:
    """A Dask ``BatchedSend``: a message leaves at once when the last batch left ``interval``
    ago, else with the next batch; it arrives ``latency`` later, where ``deliver`` runs."""

    def __init__(self, env: simpy.Environment, interval: float, latency: float, sender: _Process | None = None):
        self.env, self.interval, self.latency, self.sender = env, interval, latency, sender
        self.last = -math.inf
        self.batch: list | None = None

    def send(self, deliver) -> None:
        if self.batch is not None:
            self.batch.append(deliver)
            return
        wait = self.last + self.interval - self.env.now
        self.batch = [deliver]
        self.env.process(self._flush(max(wait, 0.0)))

    def _flush(self, wait: float) -> Proc:
        if wait > 0:
            yield self.env.timeout(wait)
        if self.sender is not None:
            yield from self.sender.loop(0.0)  # the write is a callback of the sender's event loop
        batch, self.batch = self.batch or [], None
        self.last = self.env.now
        yield self.env.timeout(self.latency)
        for deliver in batch:
            deliver()


class _Task:
    __slots__ = ("batches", "cancel", "id", "population", "prio", "rows", "seconds", "state", "stream", "worker")

    def __init__(self, tid: int, prio: tuple, population: int, batches: list[int], stream: object):
        self.id, self.prio, self.population, self.batches, self.stream = tid, prio, population, batches, stream
        self.worker: int | None = None
        self.state = "new"  # new, queued, assigned, running, finished
        self.cancel = False  # released by the client
        self.seconds = 0.0  # compute time on the worker (evaluate_on_worker's perf_counter reports it)
        self.rows = 0


class Replay:
    """One replay of ``trace`` on ``workers`` workers (see the module docstring)."""

    budget = None  # DaskExecutor's run budget: the replayed runs have none (time_cap unbounded)
    busy_s = 0.0  # DaskExecutor._measured adds to it

    def __init__(self, trace: Trace, workers: int, sim_seconds: float, costs: Costs, design: Design = Design(),
                 cluster: Replay | None = None):
        """``cluster``: another replay whose clock, scheduler and workers this one's job
        shares (``benchmarks.cluster_model.queue``: many jobs on one cluster); its runner's
        process and its client's streams are its own."""
        self.trace, self.W, self.sim_s, self.c, self.design = trace, workers, sim_seconds, costs, design
        # the worker threads the executor sizes its tasks in flight and their size on: the
        # cluster's (DaskExecutor.n_workers); a queue may give each job its share, and its tasks
        # up to MAX_TASK_SECONDS x (W / share)^task_exponent of compute time
        self.threads: Callable[[], int] = lambda: self.W
        self.task_exponent = 0.0
        self.env = simpy.Environment() if cluster is None else cluster.env
        self.runner = _Process(self.env, costs.quantum, gil=costs.convoy)
        own = design.scheduler == "own"
        self.sched = cluster.sched if cluster is not None else (
            _Process(self.env, costs.quantum, gil=False) if own else self.runner)
        env, lat = self.env, costs.latency
        # Dask's batched streams (Costs: their intervals)
        self.to_sched = _Channel(env, costs.to_scheduler_interval, lat, self.runner)
        self.to_client = _Channel(env, costs.to_client_interval, lat, self.sched)
        if cluster is not None:  # the shared scheduler's queue and the shared workers
            self.to_worker, self.from_worker, self.ids = cluster.to_worker, cluster.from_worker, cluster.ids
            self.queue, self.processing, self.ready, self.wake = cluster.queue, cluster.processing, cluster.ready, cluster.wake
            self.generation = cluster.generation
        else:
            self.to_worker = [_Channel(env, costs.to_worker_interval, lat, self.sched) for _ in range(workers)]
            self.from_worker = [_Channel(env, costs.from_worker_interval, lat) for _ in range(workers)]
            self.ids = itertools.count()
            self.queue: list = []  # the scheduler's queued tasks: (prio, id, task)
            self.processing = [0] * workers  # tasks the scheduler has given each worker
            self.ready: list[list] = [[] for _ in range(workers)]  # each worker's tasks, by priority
            self.wake: list[simpy.Event | None] = [None] * workers
            # None: one job, its tasks in (population, class, batch) order; a count: each
            # client.map a new priority generation, first, as Dask's scheduler orders many clients' tasks
            self.generation: itertools.count | None = None
        # the run starts at this population (a resume) and ends early when asked to give its
        # worker back (the service's turns: ``turn_asked``, then ``yielded_at`` the last population)
        self.first, self.turn_asked, self.yielded_at = 1, False, None
        bs = trace.batch_size
        self.bs = bs
        # worker seconds per batch beside the sleep: evaluator CPU and the codec, scaled
        self.batch_cpu = []
        for p in trace.populations:
            codec = (p.codec_us["unpack_draws"] + p.codec_us["results"]) * 1e-6
            self.batch_cpu.append([costs.worker_scale * e * 1e-6 + codec + costs.sleep_overshoot for e in p.evaluator_us])
        # accounting
        self.phase = "start"
        self.idle = workers
        self.busy_overhead = 0.0
        self.last = 0.0
        self.time: dict[str, float] = {}
        self.undelivered = 0  # tasks the main thread decided on, not yet on a worker
        self.executed = self.useful_rows = 0
        self.counted = 0
        self.expected: int | None = None  # the executor's: batches the previous stream consumed
        self.batch_seconds: float | None = None
        self.threads_at: float | None = None
        # the writer
        self.write_queue: list[int] = []
        self.write_wake: simpy.Event | None = None
        self.closing = False
        self.writer_done = self.env.event()
        self.last_append = -math.inf
        self.recorded: list[float] = []

    # -- accounting -------------------------------------------------------------------------

    def _account(self) -> None:
        now = self.env.now
        dt = now - self.last
        if dt > 0 and self.idle:
            key = self.phase
            if key == "fill":
                key = "idle: dispatch" if self.undelivered or self.queue else "idle: tail"
            self.time[key] = self.time.get(key, 0.0) + dt * self.idle
        self.last = now

    def _set_phase(self, phase: str) -> None:
        self._account()
        self.phase = phase

    def _add(self, key: str, seconds: float) -> None:
        self.time[key] = self.time.get(key, 0.0) + seconds

    # -- CPUs ---------------------------------------------------------------------------------

    def main_cpu(self, seconds: float) -> Proc:
        """The runner's main thread (or its store writer) computing."""
        yield from self.runner.cpu(seconds)

    def sched_cpu(self, seconds: float) -> Proc:
        """One callback of the scheduler's event loop."""
        yield from self.sched.loop(seconds)

    def background(self) -> Proc:
        """The scheduler process's periodic work (ticks, heartbeats): CPU per second of wall."""
        per_s = self.c.background + self.c.heartbeat * self.c.heartbeats_per_s(self.W)
        if per_s <= 0:
            return
        while True:
            yield self.env.timeout(0.1)
            self.env.process(self.sched_cpu(0.1 * per_s))

    # -- the scheduler -------------------------------------------------------------------------

    def _fill_slots(self) -> None:
        """Give queued tasks (priority order) to workers with a free slot, emptiest first."""
        while self.queue:
            w = min(range(self.W), key=lambda i: (self.processing[i], i))
            if self.processing[w] >= WORKER_SLOTS:
                return
            _, _, task = heapq.heappop(self.queue)
            self.processing[w] += 1
            task.worker, task.state = w, "assigned"
            self.to_worker[w].send(lambda task=task, w=w: self._deliver(task, w))

    def _deliver(self, task: _Task, w: int) -> None:
        self._account()
        self.undelivered -= 1
        heapq.heappush(self.ready[w], (task.prio, task.id, task))
        if self.wake[w] is not None:
            self.wake[w].succeed()  # type: ignore[union-attr]
            self.wake[w] = None

    def _update_graph(self, tasks: list[_Task]) -> Proc:
        yield from self.sched_cpu(self.c.sched_call + len(tasks) * self.c.sched_submit)
        for task in tasks:
            if task.cancel:
                self.undelivered -= 1
                continue
            task.state = "queued"
            heapq.heappush(self.queue, (task.prio, task.id, task))
        self._fill_slots()

    def _finished(self, task: _Task, w: int) -> Proc:
        yield from self.sched_cpu(self.c.sched_finish)
        self.processing[w] -= 1
        self._fill_slots()
        if not task.cancel and task.stream is not None:
            owner = task.stream.sim  # type: ignore[attr-defined]  # the job whose client gathers it
            owner.to_client.send(lambda: owner.env.process(owner._gather(task)))

    def _gather(self, task: _Task) -> Proc:
        """The client's event loop: ``as_completed(with_results=True)`` fetches the result."""
        yield from self.runner.loop(self.c.gather)
        yield self.env.timeout(self.c.gather_latency)
        if not task.cancel:
            task.stream.completed.put(task)  # type: ignore[attr-defined]

    def _released(self, tasks: list[_Task]) -> Proc:
        yield from self.sched_cpu(len(tasks) * self.c.sched_release)
        queued = [t for t in tasks if t.state == "queued"]
        if queued:
            self._account()
            self.queue[:] = [q for q in self.queue if not q[2].cancel]  # in place: a cluster's queue is shared
            heapq.heapify(self.queue)
            self.undelivered -= len(queued)
        for task in tasks:
            if task.state == "assigned" and task.worker is not None:
                self.to_worker[task.worker].send(lambda task=task: self._cancel_on_worker(task))

    def _cancel_on_worker(self, task: _Task) -> None:
        if task.state == "assigned":  # not started: the worker drops it
            w = task.worker
            assert w is not None
            self.ready[w] = [r for r in self.ready[w] if r[2] is not task]
            heapq.heapify(self.ready[w])
            task.state = "finished"
            self.processing[w] -= 1
            self._fill_slots()

    # -- workers ---------------------------------------------------------------------------------

    def worker(self, w: int) -> Proc:
        while True:
            if not self.ready[w]:
                self.wake[w] = self.env.event()
                yield self.wake[w]
                continue
            _, _, task = heapq.heappop(self.ready[w])
            if task.state != "assigned":
                continue
            self._account()
            self.idle -= 1
            task.state = "running"
            compute = task.seconds
            yield self.env.timeout(self.c.worker_task + compute)
            self._account()
            self.idle += 1
            self.busy_overhead += self.c.worker_task
            self.executed += task.rows
            self._add("simulating", compute)
            task.state = "finished"
            self.from_worker[w].send(lambda task=task, w=w: self.env.process(self._finished(task, w)))

    # -- the client's side ------------------------------------------------------------------------

    def submit(self, stream: _Stream, groups: list[list[int]], klass: int) -> Proc:
        """``client.map`` of tasks (main thread), then the scheduler's update-graph."""
        pop = stream.pop
        codec = pop.codec_us
        pack = sum(len(g) for g in groups) * (codec["draws"] * 1e-6)
        first = () if self.generation is None else (next(self.generation),)
        tasks = [_Task(next(self.ids), (*first, stream.t, klass, g[0] if g else 0), stream.t, g, stream) for g in groups]
        cpu = self.batch_cpu[stream.t - 1]
        mean = float(np.mean(cpu))
        for task in tasks:
            task.seconds = sum(self.bs * self.sim_s + (cpu[b - 1] if b - 1 < len(cpu) else mean) for b in task.batches)
            task.rows = self.bs * len(task.batches)
        self.undelivered += len(tasks)
        yield from self.main_cpu(self.c.submit_call + len(tasks) * self.c.submit_task + pack)
        self.to_sched.send(lambda: self.env.process(self._update_graph(tasks)))
        return tasks

    def release(self, tasks: list[_Task]) -> Proc:
        if not tasks:
            return
        for task in tasks:
            task.cancel = True
        yield from self.main_cpu(len(tasks) * self.c.release_task)
        self.to_sched.send(lambda: self.env.process(self._released(tasks)))

    def n_workers(self) -> Proc:
        """``DaskExecutor.n_workers``: a round trip to the scheduler at most once a second."""
        now = self.env.now
        if self.threads_at is None or now - self.threads_at > NTHREADS_INTERVAL_S:
            # an RPC of its own (no batching): there and back
            yield self.env.timeout(self.c.latency)
            yield from self.sched_cpu(self.c.sched_call)
            yield self.env.timeout(self.c.latency)
            self.threads_at = self.env.now
        return self.threads()

    def group_size(self, need: int, consumed: int, forced: int | None) -> int:
        """``DaskExecutor.group_size`` itself (it reads ``batch_seconds`` and :meth:`time_cap`),
        or the design's size."""
        if forced is not None:
            return forced
        threads = self.threads()
        longest = MAX_TASK_SECONDS * (self.W / threads) ** self.task_exponent
        return DaskExecutor.group_size(self, need, consumed, threads, longest)  # type: ignore[arg-type]

    def time_cap(self) -> int:
        """A replay has no time budget (``DaskExecutor.time_cap`` without one)."""
        return 2**62

    def measured(self, seconds: float, size: int) -> None:
        DaskExecutor._measured(self, seconds, size)  # type: ignore[arg-type]

    # -- the writer thread ---------------------------------------------------------------------------

    def writer(self) -> Proc:
        store = self.trace.store_s
        one, every, n = store["one"], store["all"], store["populations"]
        per = max(0.0, (every - one) / max(n - 1, 1))
        fixed = max(0.0, one - per)
        while True:
            while not self.write_queue and not self.closing:
                self.write_wake = self.env.event()
                yield self.write_wake
            if not self.write_queue and self.closing:
                break
            wait = self.last_append + WRITE_INTERVAL_S - self.env.now
            if wait > 0 and not self.closing:
                self.write_wake = self.env.event()
                yield self.env.any_of([self.write_wake, self.env.timeout(wait)])
                self.write_wake = None
            k = len(self.write_queue)
            self.write_queue.clear()
            self.last_append = self.env.now
            # zarr's writes run on its own event loop and I/O threads: short callbacks between
            # I/O waits, taking turns for the GIL with the other callbacks (no convoy)
            yield from self.runner.slices(self.c.store_scale * (fixed + per * k))
        self.writer_done.succeed()

    def put(self, t: int) -> None:
        self.write_queue.append(t)
        if self.write_wake is not None and not self.write_wake.triggered:
            self.write_wake.succeed()

    def close_writer(self) -> Proc:
        self.closing = True
        if self.write_wake is not None and not self.write_wake.triggered:
            self.write_wake.succeed()
        yield self.writer_done

    # -- the run ---------------------------------------------------------------------------------------

    def step_parts(self, pop: PopulationTrace) -> tuple[float, float]:
        """(finish, geometry + record) CPU seconds of a population's step."""
        r = pop.runner_s
        finish, after = r.get("finish", 0.0), r.get("geometry", 0.0) + r.get("record", 0.0)
        if self.design.step_s is not None:
            total = finish + after
            share = finish / total if total > 0 else 0.5
            return self.design.step_s * share, self.design.step_s * (1 - share)
        s = self.c.runner_scale
        return s * finish, s * after

    def lookahead_count(self, t: int, carry: bool = False) -> int:
        """L for population t (t >= 2), look-ahead batches or carried ones: a property of the
        job (a number, or a share of t's expected batches: its new particles over the batch
        size and the acceptance of the last population finished when they are asked for),
        never of the cluster or of timing."""
        d = self.design
        fixed, share = (d.carry_batches, d.carry_share) if carry else (d.lookahead_batches, d.lookahead_share)
        if t < 2 or t > len(self.trace.populations):
            return 0
        if fixed:
            return fixed
        if share <= 0:
            return 0
        pops = self.trace.populations
        known = pops[t - 3] if t >= 3 else None  # the last population finished when t - 1 opens
        acceptance = known.n_needed / known.simulations if known is not None else 0.5
        return max(1, math.ceil(share * pops[t - 1].n_needed / (self.bs * acceptance)))

    def main(self) -> Proc:
        c, trace = self.c, self.trace
        pops, store = trace.populations, trace.store_s
        # run_job: the store created, marked running; the executor: the job's data and the
        # anchors (2 W + 1 no-op tasks held for the run), after asking for the worker count
        # (a resume reads the stored populations back instead of creating the store)
        yield from self.main_cpu(c.store_scale * (store["read" if self.first > 1 else "create"] + store["status"]))
        yield from self.n_workers()
        anchors = _Stream(self, pops[0], None)
        held = yield from self.submit(anchors, [[]] * (2 * self.W + 2), 0)
        for task in held:  # type: ignore[attr-defined]
            task.stream = None  # held, never gathered
        stream = yield from self.open(self.first, None)
        for t in range(self.first, len(pops) + 1):
            pop = pops[t - 1]
            self._set_phase("fill")
            yield from self.fill(t, stream)
            self._set_phase("step")
            finish, after = self.step_parts(pop)
            yield from self.main_cpu(finish)
            if t < len(pops):
                stream = yield from self.open(t + 1, stream)
            else:
                self._set_phase("end")
            yield from self.main_cpu(after)
            self.recorded.append(self.env.now)  # the population's elapsed_s
            self.put(t)
            if self.turn_asked and t < len(pops):  # the service releases the loop's task after this population
                yield self.env.timeout(TURN_RELEASE_S)
                yield from stream.close()  # the next population's tasks released: its rows so far are lost
                self.yielded_at = t
                break
        yield from self.close_writer()
        # the final status, and the result read back from the store (run_job's return)
        yield from self.main_cpu(c.store_scale * (store["status"] + store["read"]))
        self._set_phase("done")
        self.end = self.env.now

    def open(self, t: int, previous: _Stream | None) -> Proc:
        """Open population t (``Filling``: ``executor.map``, then the caller's first hint);
        with look-ahead, the look-ahead batches of t + 1 are submitted too."""
        pop = self.trace.populations[t - 1]
        stream = _Stream(self, pop, previous.lookahead_next if previous is not None else None)
        stream.W = yield from self.n_workers()
        if stream.lookahead is None:
            yield from stream.expect(pop.n_needed / self.bs, at_least=True)
        else:
            # the filling knows what its look-ahead batches hold (those done: counted; the rest:
            # at the share measured so far), and asks for the regular batches the remainder
            # needs at the last finished population's acceptance, 10 % more
            left = max(pop.n_needed - stream.lookahead.expected_kept(), 0.0)
            done = self.trace.populations[t - 2]
            yield from stream.expect(left / (self.bs * done.n_needed / done.simulations))
        self._set_phase("fill")
        la = self.lookahead_count(t + 1) if t < len(self.trace.populations) else 0
        if la:
            # one client.map of L batches, each task at a priority below every regular batch of t
            prefix = _Prefix(self, self.trace.populations[t], simpy.Store(self.env), set())
            size = self.design.task_batches or max(1, self.group_size(la, 0, None))
            groups = [list(range(i, min(i + size, la + 1))) for i in range(1, la + 1, size)]
            tasks = yield from self.submit(prefix, groups, 0)  # type: ignore[arg-type]
            prefix.add(tasks)  # type: ignore[arg-type]
            stream.lookahead_next = prefix
        return stream

    def fill(self, t: int, stream: _Stream) -> Proc:
        """``Filling.finish``: results in order (look-ahead ones first) until the population is full."""
        pop = stream.pop
        consume = self.c.runner_scale * pop.runner_s.get("consume", 0.0) / max(len(pop.accepted), 1)
        kept = 0.0
        la = stream.lookahead
        if la is not None:
            while la.entries:
                yield from la.next()
                yield from self.main_cpu(consume)
                kept += la.kept_per_batch
                self.counted += self.bs
                if kept >= pop.n_needed:
                    break
            yield from la.close()
        n_batches = 0
        kept_regular = 0
        b = 0
        while kept < pop.n_needed:
            yield from stream.next()
            yield from self.main_cpu(consume)
            a = pop.accepted[b] if b < len(pop.accepted) else pop.n_needed / max(len(pop.accepted), 1)
            b += 1
            kept += a
            kept_regular += a
            if kept >= pop.n_needed:
                missing = pop.n_needed - (kept - a)
                self.counted += math.ceil(missing / a * self.bs) if a > 0 else self.bs
                break
            self.counted += self.bs
            n_batches += 1
            yield from stream.expect((pop.n_needed - kept) * n_batches / max(kept_regular, 0.5))
        carry = self.lookahead_count(t + 1, carry=True)
        if carry:
            yield from stream.hand_over(b, carry, self.trace.populations[t])
        else:
            yield from stream.close()

    def run(self) -> Outcome:
        env = self.env
        for w in range(self.W):
            env.process(self.worker(w))
        env.process(self.writer())
        env.process(self.background())
        done = env.process(self.main())
        env.run(until=done)
        self._account()
        wall = self.end
        sims = self.trace.simulations
        self._add("task overhead", self.busy_overhead)
        useful = sims * self.sim_s
        # simulating time splits into the rows the run uses and the rest (surplus, dropped look-ahead rows)
        simulating = self.time.pop("simulating", 0.0)
        self.time["useful"] = useful
        self.time["surplus"] = max(0.0, simulating - useful)
        steady = math.nan
        if len(self.recorded) > 1:
            later = sum(p.simulations for p in self.trace.populations[1:]) * self.sim_s
            steady = later / (self.W * (self.recorded[-1] - self.recorded[0]))
        return Outcome(self.W, wall, useful / (self.W * wall), sims, self.executed, self.counted,
                       dict(self.time), self.runner.busy, self.sched.busy, steady)


class _Stream:
    """One ``DaskExecutor.map`` call: ``Stream``'s policies, on the model's clock."""

    def __init__(self, sim: Replay, pop: PopulationTrace, lookahead: _Prefix | None):
        self.sim, self.pop, self.t = sim, pop, pop.t
        self.lookahead = lookahead
        self.lookahead_next: _Prefix | None = None
        self.W = sim.W
        self.need = math.ceil(NEED_MARGIN * sim.expected) if sim.expected is not None else None
        self.left: int | None = self.need
        self.consumed = self.submitted = 0
        self.carry = sim.lookahead_count(self.t + 1, carry=True)
        self.pending: deque[_Task] = deque()
        self.done: set[int] = set()
        self.completed = simpy.Store(sim.env)
        self.ready: deque[int] = deque()
        self.closed = False
        self.next_batch = 1

    def expect(self, batches: float, at_least: bool = False) -> Proc:
        if at_least and self.consumed == 0:
            least = math.ceil(batches)
            self.left = max(least, self.need) if self.need is not None else max(2 * least, self.W)
        else:
            self.left = math.ceil(NEED_MARGIN * batches)
        if not self.closed:
            yield from self.top_up()

    def in_flight(self) -> int:
        return len(self.pending) - len(self.done)

    def top_up(self) -> Proc:
        sim = self.sim
        groups: list[list[int]] = []
        want = max(self.left or 1, 1) + self.carry  # with carry-over: the next population's first batches too
        room = IN_FLIGHT_PER_THREAD * self.W - self.in_flight()
        while (self.submitted - self.consumed < want and len(groups) < room) or len(self.pending) + len(groups) == 0:
            size = sim.group_size(want, self.consumed, sim.design.task_batches)
            groups.append(list(range(self.next_batch, self.next_batch + size)))
            self.next_batch += size
            self.submitted += size
        if groups:
            tasks = yield from sim.submit(self, groups, 1)
            self.pending.extend(tasks)  # type: ignore[arg-type]

    def next(self) -> Proc:
        sim = self.sim
        while not self.ready:
            yield from self.top_up()
            task = self.pending[0]
            while task.id not in self.done:
                got = yield self.completed.get()
                self.done.add(got.id)  # type: ignore[attr-defined]
                if self.in_flight() < sim.design.refill * self.W:
                    yield from self.top_up()
            self.done.discard(task.id)
            self.pending.popleft()
            sim.measured(task.seconds, len(task.batches))
            unpack = len(task.batches) * self.pop.codec_us["unpack_results"] * 1e-6
            yield from sim.main_cpu(unpack)
            self.ready.extend(task.batches)
        self.consumed += 1
        return self.ready.popleft()

    def close(self) -> Proc:
        if self.closed:
            return
        self.closed = True
        self.sim.expected = max(self.consumed, 1)
        tasks = list(self.pending)
        self.pending.clear()
        self.done.clear()
        yield from self.sim.release(tasks)

    def hand_over(self, last: int, n: int, following: PopulationTrace) -> Proc:
        """Close, keeping batches last + 1 .. last + n for the next population (``Design.carry``):
        those already here, the tasks that hold them (submitting any not yet submitted); the
        rest released."""
        self.closed = True
        self.sim.expected = max(self.consumed, 1)
        prefix = _Prefix(self.sim, following, self.completed, self.done)
        prefix.entries.extend((b, None) for b in self.ready if b <= last + n)
        keep, drop = [], []
        for task in self.pending:
            (keep if task.batches[0] <= last + n else drop).append(task)
        prefix.add(keep)
        self.pending.clear()
        yield from self.sim.release(drop)
        have = max([last, *(b for b, _ in prefix.entries)])
        if have < last + n:  # the rest, cut into tasks as a top-up would
            size = self.sim.group_size(last + n - have, self.consumed, self.sim.design.task_batches)
            groups = [list(range(b, min(b + size, last + n + 1))) for b in range(have + 1, last + n + 1, size)]
            tasks = yield from self.sim.submit(self, groups, 1)
            prefix.add(tasks)  # type: ignore[arg-type]
        self.lookahead_next = prefix


class _Prefix:
    """Batches a population consumes before its regular ones, in order: its look-ahead
    batches (submitted when the previous population opened, behind its regular batches) or
    the previous population's batches after its last consumed one (``Design.carry``). Each
    yields the accepted rows of a look-ahead batch (rows drawn from the previous bounds that
    fall inside this population's, below its tolerance: measured, ``PopulationTrace.lookahead``)."""

    def __init__(self, sim: Replay, pop: PopulationTrace, completed: simpy.Store, done: set[int]):
        self.sim, self.pop, self.t = sim, pop, pop.t
        la = pop.lookahead or {"accept": 0.0}
        self.kept_per_batch = float(la["accept"]) * sim.bs
        self.entries: deque[tuple[int, _Task | None]] = deque()  # (batch, its task; None: its result is here)
        self.completed, self.done = completed, done
        self.closed = False

    @property
    def n(self) -> int:
        return len(self.entries)

    def expected_kept(self) -> float:
        return self.kept_per_batch * self.n

    def add(self, tasks: list[_Task]) -> None:
        for task in tasks:
            self.entries.extend((b, task) for b in task.batches)

    def next(self) -> Proc:
        batch, task = self.entries.popleft()
        if task is not None:
            while task.id not in self.done:
                got = yield self.completed.get()
                self.done.add(got.id)  # type: ignore[attr-defined]
            # the task's results unpacked once, with its first batch
            for i, (b, other) in enumerate(self.entries):
                if other is task:
                    self.entries[i] = (b, None)
            unpack = len(task.batches) * self.pop.codec_us["unpack_results"] * 1e-6
            yield from self.sim.main_cpu(unpack)
        return batch

    def close(self) -> Proc:
        if self.closed:
            return
        self.closed = True
        tasks = list({id(task): task for _, task in self.entries if task is not None}.values())
        self.entries.clear()
        yield from self.sim.release(tasks)


class Pattern(Replay):
    """Dask alone, without the algorithm: tasks that only sleep ``seconds``, as
    ``benchmarks.scale.dask_floor`` (``"floor"``: ``rounds`` populations of ``units`` tasks,
    one ``client.map`` each, gathered as they complete, the next after the last) or the
    16-core file's "Dask alone" runs (``"fed"``: ``2 W`` tasks in flight, one submitted as each
    completes, for ``duration`` seconds). Efficiency: seconds slept over W x wall."""

    def __init__(self, kind: str, workers: int, seconds: float, costs: Costs, units: int = 0, rounds: int = 0,
                 duration: float = 8.0, design: Design = Design()):
        self.kind, self.units, self.rounds, self.seconds, self.duration = kind, units, rounds, seconds, duration
        empty = PopulationTrace(t=1, epsilon=1.0, n_needed=1, accepted=[1], evaluator_us=[0.0], simulations=1,
                                runner_s={}, codec_us={"draws": 0, "unpack_draws": 0, "results": 0, "unpack_results": 0})
        trace = Trace("pattern", {"batch_size": 1}, {}, {"create": 0, "one": 0, "all": 0, "populations": 1, "status": 0,
                                                          "read": 0}, [empty])
        super().__init__(trace, workers, seconds, costs.scaled(sleep_overshoot=costs.sleep_overshoot), design)
        self.slept = 0.0

    def _tasks(self, stream: _Stream, n: int) -> Proc:
        tasks = yield from self.submit(stream, [[1]] * n, 1)
        return tasks

    def main(self) -> Proc:
        stream = _Stream(self, self.trace.populations[0], None)
        self._set_phase("fill")
        if self.kind == "floor":
            previous: list[_Task] = []
            for _ in range(self.rounds):
                tasks = yield from self._tasks(stream, self.units)
                yield from self.release(previous)  # the old list of futures dropped
                for _ in tasks:  # type: ignore[attr-defined]
                    yield stream.completed.get()
                previous = tasks  # type: ignore[assignment]
                self.slept += self.units * self.seconds
        else:
            start = self.env.now
            yield from self._tasks(stream, 2 * self.W)
            while self.env.now - start < self.duration:
                yield stream.completed.get()
                self.slept += self.seconds
                yield from self._tasks(stream, 1)
        self._set_phase("done")
        self.end = self.env.now

    def run(self) -> Outcome:
        out = super().run()
        out.efficiency = self.slept / (self.W * out.wall)
        return out


def replay(trace: Trace, workers: int, sim_seconds: float, costs: Costs, design: Design = Design()) -> Outcome:
    return Replay(trace, workers, sim_seconds, costs, design).run()
