"""The queue of jobs (issue U): many jobs on one cluster, no barrier between them.

Each job is a replayed trace (:class:`benchmarks.cluster_model.model.Replay`) whose loop
holds one worker's job slot (``service.run.jobs``: one job loop per worker process, the
service's dispatcher starts the queue's head whenever a slot is free); all the jobs share
the cluster's clock, its one scheduler (its own process, as under `abcns serve` or
``run_jobs``: never a job loop's) and its workers, so while one job is at its population's
barrier (its tail, its step) the other jobs' batches fill the workers. Tasks are ordered as
Dask's scheduler orders many clients' tasks: each ``client.map`` a new priority generation.

What a job costs besides its run, as the service and ``run_jobs`` do it:

- **placement** (``service.run.jobs.place``): the job task first times the job's evaluator
  on its worker, a warm-up call of one batch, then calls until ``PILOT_S`` is spent (at
  most ``PILOT_CALLS``), unless the warm-up already puts a population under the limit;
  then the job runs *whole* (the in-process engine, the worker's thread held to its end) or
  *spreads* (the task secedes: its thread goes to the batches, its loop stays);
- **dispatch**: ``dispatch_s`` from a slot freeing to the next job task starting on it (the
  caller's look at the free slots, the submission, the task's way to the worker: measured
  by ``benchmarks.jobs``, the workers' idle gaps between jobs);
- **turns** (``--turn-s``, the service's 30 s): while jobs wait and no slot is free, the
  dispatcher (every second) asks the job that has run longest since it last started, if
  ``turn_s`` or more, to give its slot back after its current population; the service
  releases its loop's task (``TURN_RELEASE_S``), the next population's rows are lost, the
  job goes to the back of the queue and resumes from its store (its executor starts anew).

A *whole* job is its worker busy for its populations' time (each population its measured
serial time: ``whole_seconds``), no tasks. The queue's *utilization* is what `/health`
shows: the jobs' useful simulation seconds (the trace's simulations of every population a
job completed, x the time of one) over workers x wall.

Not modelled: a job loop's CPU on the worker process it shares with that worker's batches
(a sleeping simulator leaves that process's GIL free; a computing one would not); a mix of
whole and spread jobs in one queue; the service's own process (HTTP, events).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

import simpy

from benchmarks.cluster_model.costs import Costs
from benchmarks.cluster_model.model import Design, Replay, _Task
from benchmarks.cluster_model.trace import Trace
from service.run.dask_executor import LOCAL_POPULATION_S, MAX_TASK_SECONDS
from service.run.jobs import PILOT_CALLS, PILOT_S, limit_seconds

#: the service's dispatcher looks again after this when nothing woke it (JobManager._dispatch)
DISPATCH_LOOK_S = 1.0


@dataclass
class QueueOutcome:
    workers: int
    jobs: int
    wall: float
    utilization: float
    starts: int  # job loops started (resumes after a turn included)
    whole: bool  # the jobs ran whole on their workers (else spread)
    pilot_s: float  # one job's placement pilot
    time: dict[str, float]
    scheduler_busy: float = 0.0  # the scheduler's CPU, seconds


def pilot(batch_s: float, particles: int, batch_size: int, threads: int) -> tuple[float, bool]:
    """(seconds the placement pilot takes, whether the job then runs whole) for a batch
    costing ``batch_s``: ``service.run.jobs.simulation_seconds`` and ``place``'s rule."""
    limit = limit_seconds(LOCAL_POPULATION_S, threads)
    if math.isinf(limit):
        return 0.0, True
    if batch_s / batch_size * particles <= limit:
        return batch_s, True
    spent, calls = 0.0, 0
    while calls < PILOT_CALLS and spent < PILOT_S:
        spent, calls = spent + batch_s, calls + 1
    return batch_s + spent, batch_s / batch_size * particles <= limit


class QueueReplay(Replay):
    """``jobs`` replays of ``trace`` on one cluster of ``workers`` single-threaded workers,
    started as job slots free (see the module docstring). ``whole_s``: for jobs that run
    whole, each job's populations' seconds (job i takes entry i modulo their number; None: the
    placement rule decides from the trace, and a spread job replays its trace); ``pilot_s``:
    the placement's pilot (None: as :func:`pilot` says for the trace's batches); ``spread``:
    every job spreads whatever the rule says (a job alone as ``benchmarks.scale`` runs it);
    ``share_exponent``: None, or each spread job's executor sizes its tasks in flight and their
    size on its share of the worker threads (the threads over the spread jobs running, at least
    one) instead of the whole cluster's, its tasks up to ``MAX_TASK_SECONDS`` x (threads /
    share)^``share_exponent`` of compute time (a design, not built: docs/benchmarks.md);
    ``contention_s``: CPU seconds per job of the processes besides the workers (the caller or
    the service, the scheduler), added to each whole job's time: on a machine with no core
    to spare (as many workers as cores) that CPU is taken from the workers' cores."""

    def __init__(self, trace: Trace, jobs: int, workers: int, sim_seconds: float, costs: Costs,
                 dispatch_s: float = 0.0, turn_s: float | None = None, whole_s: list[list[float]] | None = None,
                 pilot_s: float | None = None, spread: bool = False, contention_s: float = 0.0,
                 share_exponent: float | None = None):
        super().__init__(trace, workers, sim_seconds, costs, Design(scheduler="own"))
        self.share_exponent = share_exponent
        self.generation = itertools.count()
        self.n_jobs, self.dispatch_s, self.turn_s, self.whole_s = jobs, dispatch_s, turn_s, whole_s
        self.contention_s = contention_s
        cpu = [x for c in self.batch_cpu for x in c]
        batch_s = trace.batch_size * sim_seconds + sum(cpu) / max(len(cpu), 1)
        measured, whole = pilot(batch_s, int(trace.job.get("particles", 1000)), trace.batch_size, workers)
        self.pilot_s = measured if pilot_s is None else pilot_s
        self.whole = whole_s is not None
        if whole and not (self.whole or spread):
            raise ValueError("the placement rule runs these jobs whole: give each population's seconds (whole_s)")
        self.waiting: deque[tuple[int, int]] = deque((i, 1) for i in range(jobs))  # (job, first population)
        self.free = list(range(workers))  # workers whose job slot is free
        self.running: dict[int, tuple[Replay | None, float, list[bool]]] = {}  # job -> (its run, since, turn)
        self.useful = 0.0
        self.starts = 0
        self.slot_freed: simpy.Event = self.env.event()
        self.pilots: dict[int, simpy.Event] = {}  # a job task's own time on its worker -> its end

    def _account(self) -> None:
        """The cluster's idle worker time, in one figure."""
        now = self.env.now
        if now > self.last and self.idle:
            self.time["idle"] = self.time.get("idle", 0.0) + (now - self.last) * self.idle
        self.last = now

    def main(self):  # type: ignore[override]
        """``JobManager._dispatch``: the queue's head to each free slot, turns while jobs wait."""
        while self.waiting or self.running:
            while self.waiting and self.free:
                job, first = self.waiting.popleft()
                turn = [False]
                self.running[job] = (None, self.env.now, turn)
                self.env.process(self.job(job, first, self.free.pop(0), turn))
            if self.waiting and self.turn_s is not None:
                self.end_a_turn()
            self.slot_freed = self.env.event()
            yield self.env.any_of([self.slot_freed, self.env.timeout(DISPATCH_LOOK_S)])
        self.end = self.env.now

    def end_a_turn(self) -> None:
        """``JobManager._end_a_turn``: one request at a time, to the job longest since its start."""
        if any(turn[0] for _, _, turn in self.running.values()):
            return
        assert self.turn_s is not None
        due = [(since, job) for job, (_, since, _) in self.running.items() if self.env.now - since >= self.turn_s]
        if due:
            run, _, turn = self.running[min(due)[1]]
            turn[0] = True
            if run is not None:
                run.turn_asked = True

    def populations(self, job: int) -> list[float] | None:
        """A whole job's populations' seconds (None: a spread job, its trace's)."""
        return None if self.whole_s is None else self.whole_s[job % len(self.whole_s)]

    def job(self, job: int, first: int, w: int, turn: list[bool]):
        """One job task on worker ``w``'s slot: dispatch, the pilot (the task on the worker's
        thread), then its run whole (the thread held) or spread (its own loop, the tasks)."""
        self.starts += 1
        yield self.env.timeout(self.dispatch_s)
        whole = self.populations(job)
        if whole is not None:
            last = yield from self.whole_job(whole, first, turn)
        else:
            if self.pilot_s > 0:
                yield from self.on_worker(w, self.pilot_s)
            run = Replay(self.trace, self.W, self.sim_s, self.c, Design(scheduler="own"), cluster=self)
            run.first, run.turn_asked = first, turn[0]
            if self.share_exponent is not None:
                run.threads = lambda: max(1, self.W // max(1, sum(r is not None for r, _, _ in self.running.values())))
                run.task_exponent = self.share_exponent
            self.running[job] = (run, self.running[job][1], turn)
            self.env.process(run.writer())
            yield from run.main()
            last = run.yielded_at or len(self.trace.populations)
            self.useful += sum(p.simulations for p in self.trace.populations[first - 1:last]) * self.sim_s
        del self.running[job]
        if last < len(whole or self.trace.populations):
            self.waiting.append((job, last + 1))  # behind the jobs that waited
        self.free.append(w)
        if not self.slot_freed.triggered:
            self.slot_freed.succeed()

    def whole_job(self, seconds: list[float], first: int, turn: list[bool]):
        """A whole job: its worker busy for the pilot, then population after population
        until its last or the end of its turn; returns the last population it made."""
        self._account()
        self.idle -= 1
        yield self.env.timeout(self.pilot_s + self.contention_s)
        self._add("simulating", self.pilot_s + self.contention_s)
        t = first
        for t in range(first, len(seconds) + 1):
            yield self.env.timeout(seconds[t - 1])
            self.useful += seconds[t - 1]
            if turn[0] and t < len(seconds):
                break
        self._account()
        self.idle += 1
        return t

    def on_worker(self, w: int, seconds: float):
        """A job task's own time on worker ``w``'s thread (``seconds``), queued there as any
        task, first in its order."""
        task = _Task(next(self.ids), (-1,), 0, [], None)
        task.seconds = seconds
        done = self.env.event()
        self.pilots[task.id] = done
        self.processing[w] += 1
        task.worker, task.state = w, "assigned"
        self.undelivered += 1
        self.to_worker[w].send(lambda: self._deliver(task, w))
        yield done

    def _finished(self, task, w):  # type: ignore[override]
        done = self.pilots.pop(task.id, None)
        if done is not None:
            done.succeed()
        yield from super()._finished(task, w)

    def run(self) -> QueueOutcome:  # type: ignore[override]
        env = self.env
        for w in range(self.W):
            env.process(self.worker(w))
        env.process(self.background())
        done = env.process(self.main())
        env.run(until=done)
        self._account()
        self.time["task overhead"] = self.busy_overhead
        simulating = self.time.pop("simulating", 0.0) + (self.whole_s is not None) * self.useful
        self.time["useful"] = self.useful
        self.time["other work"] = max(0.0, simulating - self.useful)  # surplus, pilots, rows lost at a turn
        return QueueOutcome(self.W, self.n_jobs, self.end, self.useful / (self.W * self.end), self.starts, self.whole,
                            self.pilot_s, dict(self.time), self.sched.busy)


def queue(trace: Trace, jobs: int, workers: int, sim_seconds: float, costs: Costs, **kw) -> QueueOutcome:
    return QueueReplay(trace, jobs, workers, sim_seconds, costs, **kw).run()


#: the dispatch measured through the service on the 2-core machine (`benchmarks.jobs --service`,
#: 16 §4.1 jobs on 2 workers: the median gap on a worker between one job task's end and the next
#: one's start, 59 ms under load 7-9; run_jobs: 135 ms, before its wake-up on a job's end)
DISPATCH_S = 0.06
#: run_jobs's dispatch, measured the same way after its wake-up on a job's end: 34-49 ms
RUN_JOBS_DISPATCH_S = 0.04
#: the queues printed by ``queue``: (trace, ms a simulation)
QUEUES = [("evidence-1000-warm", 2.0), ("evidence-1000-warm", 20.0)]


def print_queue(workers: list[int], jobs: list[int] | None, queues: list[tuple[str, float]], dispatch_s: float,
                turn_s: float | None, share_exponent: float | None = None) -> None:
    """The predicted utilization of queues of spread jobs (each a replay of a trace) at each
    worker count, as many jobs as workers unless ``jobs`` says (one per worker count)."""
    from benchmarks.cluster_model.study import design_costs

    costs = design_costs()
    print(f"costs: {costs.name}; own scheduler; dispatch {1e3 * dispatch_s:g} ms a job; turns "
          f"{'none' if turn_s is None else f'{turn_s:g} s'}; the jobs' loops each on a worker's slot; tasks in flight "
          + (f"sized on each job's share of the worker threads, tasks up to (threads / share)^{share_exponent:g} x "
             f"{MAX_TASK_SECONDS:g} s" if share_exponent is not None else "sized on all the worker threads"))
    print("| trace | ms / simulation | workers | jobs | utilization | one job alone | wall s | starts | pilot s | "
          "idle | other work | task overhead | scheduler busy |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, ms in queues:
        trace = Trace.load(name)
        for i, w in enumerate(workers):
            n = jobs[i] if jobs else w
            out = queue(trace, n, w, ms / 1e3, costs, dispatch_s=dispatch_s, turn_s=turn_s, share_exponent=share_exponent)
            alone = queue(trace, 1, w, ms / 1e3, costs, pilot_s=0.0, spread=True).utilization
            sh = {k: v / (w * out.wall) for k, v in out.time.items()}
            print(f"| {name} | {ms:g} | {w} | {n} | **{out.utilization:.2f}** | {alone:.2f} | {out.wall:.1f} | "
                  f"{out.starts} | {out.pilot_s:.2f} | {sh.get('idle', 0):.2f} | {sh.get('other work', 0):.2f} | "
                  f"{sh.get('task overhead', 0):.2f} | {out.scheduler_busy / out.wall:.2f} |", flush=True)


def validation_rows() -> list[tuple[str, int, float, float]]:
    """(what, workers, measured, predicted) utilization: the 16-core single-job rows (a queue
    of one job, no pilot: a job alone, as benchmarks.scale ran it) and the 2-core queues of
    whole §4.1 jobs (``measured.QUEUE_2_CORES``: the jobs' time alone, the dispatch and the
    other processes' CPU per job; the measured utilization is the time alone over workers x
    wall)."""
    from benchmarks.cluster_model import measured
    from benchmarks.cluster_model.study import design_costs

    rows = []
    for (name, ms, w), (eff, _) in measured.PREDICTED_THEN_MEASURED.items():
        out = queue(Trace.load(name), 1, w, ms / 1e3, design_costs(), pilot_s=0.0, spread=True)
        rows.append((f"16 cores, one job, {name}, {ms:g} ms", w, eff, out.utilization))
    from benchmarks.cluster_model.study import local_costs

    for (name, ms, jobs, w), runs in measured.QUEUE_SLEEPY_2_CORES.items():
        out = queue(Trace.load(name), jobs, w, ms / 1e3, local_costs("evidence"), dispatch_s=RUN_JOBS_DISPATCH_S)
        rows += [(f"2 cores, {jobs} sleepy {ms:g} ms jobs, run_jobs", w, m, out.utilization) for m in runs]
    stand_in = Trace.load("evidence-1000-warm")  # whole jobs replay no trace: their times are given
    for label, run in measured.QUEUE_2_CORES.items():
        each, w = run["alone_s"], run["workers"]
        for path, wall in run["walls"].items():
            dispatch, cpu = run["gap_s"].get(path, 0.0), run["other_cpu_s"].get(path, 0.0)
            out = queue(stand_in, len(each), w, 0.002, design_costs(), dispatch_s=dispatch,
                        whole_s=[[d] for d in each], pilot_s=0.0, contention_s=cpu)
            rows.append((f"2 cores, {label}, {path}", w, sum(each) / (w * wall), out.utilization))
    return rows


def print_validation() -> bool:
    from benchmarks.cluster_model.study import TOLERANCE

    rows = validation_rows()
    print("| run | workers | measured | predicted | difference | within |")
    print("|---|---:|---:|---:|---:|---|")
    for what, w, m, p in rows:
        print(f"| {what} | {w} | {m:.2f} | {p:.2f} | {p - m:+.2f} | {'yes' if abs(p - m) <= TOLERANCE else '**no**'} |")
    ok = sum(abs(p - m) <= TOLERANCE for _, _, m, p in rows)
    print(f"\n{ok} of {len(rows)} rows within {TOLERANCE}; the 16-core queue rows are not measured yet "
          "(benchmarks/device_u.sh)")
    return ok == len(rows)
