"""The cluster model's cost parameters, in one place, each with its source.

Seconds throughout. :class:`Costs` is one machine's set; ``study.sixteen_costs`` and
``study.local_costs`` build them for the 16-core machine of
benchmarks/measurements/2026-11-25-16-cores.md and for this 2-core machine (measured by
``python -m benchmarks.cluster_model costs``): Dask's CPU per task and per second fitted to
each session's Dask floor (:func:`fit_runner_cpu`), the rest measured or stated below. The
runner's own work (step, consumption, codec, store) comes from the trace, recorded on the
2-core machine and carried to another by ``runner_scale`` and ``store_scale``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace


@dataclass(frozen=True)
class Costs:
    """Per-task and per-message costs of Dask, the runner's process and the workers.

    Runner's process (main thread): ``submit_call`` per ``client.map`` call,
    ``submit_task`` per task in it (beside pack_draws, from the trace), ``release_task`` per
    future released. Scheduler (the runner's process for a LocalCluster, else its own):
    ``sched_call`` per message from the client (an update-graph, an nthreads query),
    ``sched_submit`` per task taken, ``sched_finish`` per finished task (its transitions, the
    next task to that worker, the client told), ``sched_release`` per released task.
    Client's event loop: ``gather`` per completed task (``as_completed(with_results=True)``
    fetching the result), then ``gather_latency`` of waiting beside that CPU.
    Worker: ``worker_task`` of wall per task beside its batches. ``latency``: one message
    between two processes. ``background``: CPU per second of the scheduler's process while
    tasks run (event loop ticks, work stealing, the client's own), plus ``heartbeat`` per
    worker heartbeat (Dask asks for one every 0.5 s up to 10 workers, 1 s up to 50, 2 s up
    to 200, then 200 a second). ``quantum``: the GIL's switch interval.
    ``runner_scale``: the runner's CPU from the trace (step, consumption, codec, store) times
    this (the machine's speed against the trace's); ``worker_scale``: the same for the
    evaluator; ``sleep_overshoot``: what ``time.sleep`` adds per batch."""

    name: str
    submit_call: float
    submit_task: float
    release_task: float
    sched_call: float
    sched_submit: float
    sched_finish: float
    sched_release: float
    gather: float
    gather_latency: float
    worker_task: float
    latency: float
    background: float
    heartbeat: float
    sleep_overshoot: float
    runner_scale: float = 1.0
    worker_scale: float = 1.0
    quantum: float = 0.005
    #: Dask's batched streams: a message waits until the last batch on its stream left this
    #: long ago (distributed 2026.8's BatchedSend intervals: client -> scheduler 10 ms,
    #: scheduler -> client 2 ms, scheduler -> worker 5 ms, worker -> scheduler 2 ms)
    #: the GIL's convoy effect on the runner's event loop (False: plain round robin)
    convoy: bool = True
    #: the trace's store costs times this (zarr's Python and I/O: not scaled with the step)
    store_scale: float = 1.0
    to_scheduler_interval: float = 0.010
    to_client_interval: float = 0.002
    to_worker_interval: float = 0.005
    from_worker_interval: float = 0.002
    sources: dict[str, str] = field(default_factory=dict, compare=False)

    def scaled(self, **changes: float | bool) -> Costs:
        return replace(self, **changes)

    def heartbeats_per_s(self, workers: int) -> float:
        """distributed.scheduler.heartbeat_interval, inverted and summed over workers."""
        if workers <= 10:
            interval = 0.5
        elif workers < 50:
            interval = 1.0
        elif workers < 200:
            interval = 2.0
        else:
            interval = workers / 200 + 1
        return workers / interval


#: zero everywhere: the model's trivial cases (tests)
FREE = Costs("free", 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, to_scheduler_interval=0, to_client_interval=0,
             to_worker_interval=0, from_worker_interval=0)


# -- the parameters of a machine ---------------------------------------------------------------

#: how the event loops' CPU per task splits between the scheduler's steps and the client's
#: gather. The client's part (0.4) is measured: a stock scheduler on the 2-core machine takes
#: 1.4-1.8 ms per task, the client's loop 0.75-1.2 (benchmarks/measurements/2026-11-25-2-cores.md).
#: The scheduler's part is split over its steps by the Dask-floor rows (its timing, not its
#: volume, depends on the split: the floor's waves turn round faster when less is spent at
#: submission): of the candidates 20/30/12 %, 10/40/10 % and 5/45/10 % of the per-task CPU at
#: submission / completion / release, the last lands every floor row of both machines within
#: 0.03 (the first misses four by 0.05-0.06); a fitted parameter
LOOP_SPLIT = {"sched_submit": 0.05, "sched_finish": 0.45, "sched_release": 0.10, "gather": 0.40}
#: the runner's main thread per ``client.map`` call and per task, measured on the 2-core machine
#: (``costs``: 0.44-0.61 ms per call, 0.004-0.008 ms per task submitted, 0.02 released)
MAIN_CALL, MAIN_TASK = 0.55e-3, 0.005e-3
#: Linux's sleep overshoot on an idle machine (timer slack 50 µs plus wake-up): assumed
OVERSHOOT = 0.1e-3
#: one message between two processes on one machine (loopback TCP and an event-loop wake-up):
#: assumed; a gather (as_completed with results) waits for two round trips beside its CPU
LATENCY = 0.3e-3


def from_dask_figures(name: str, per_task: float, per_call: float, background: float, worker_task: float,
                      runner_scale: float, worker_scale: float, sources: dict[str, str], store_scale: float = 1.0) -> Costs:
    """Costs from the runner process's CPU per task and per ``client.map`` call (client and
    scheduler together), its CPU per second, and the worker's overhead per task."""
    loop_task = per_task - 2 * MAIN_TASK
    split = {k: v * loop_task for k, v in LOOP_SPLIT.items()}
    return Costs(name, submit_call=MAIN_CALL, submit_task=MAIN_TASK, release_task=MAIN_TASK,
                 sched_call=per_call - MAIN_CALL, gather_latency=4 * LATENCY, worker_task=worker_task,
                 latency=LATENCY, background=background, heartbeat=0.0, sleep_overshoot=OVERSHOOT,
                 runner_scale=runner_scale, worker_scale=worker_scale, store_scale=store_scale, sources=sources,
                 **split)


def fit_runner_cpu(session, per_call: float) -> tuple[float, float]:
    """(per task, per second) of the runner process's CPU, least squares over a session's
    Dask-floor rows: CPU per task = a + c / units + B x wall / tasks, the wall from the row's
    efficiency, ``c`` (per ``client.map`` call) given."""
    import numpy as np

    rows, rhs = [], []
    tasks = session.units * session.rounds
    for w, (eff, cpu_ms) in session.floor.items():
        wall = tasks * 0.05 / (w * eff)
        rows.append([1.0, wall / tasks])
        rhs.append(1e-3 * cpu_ms - per_call / session.units)
    a, b = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    return float(a), float(b)
