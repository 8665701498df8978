"""Admission limits of the HTTP service (issue K): what one job may ask of a shared machine.

``admit(spec, job, limits)`` is called when a job is submitted, after the spec is valid
(``service.spec.build``): it refuses a job over a limit with a SpecError naming the field
and the limit (HTTP 422), or one that cannot mean anything (``service.spec.check_meaningful``:
a record too short, constant or of no measured scale, a sampling rate against the models'
natural frequencies, a first tolerance below reach), and returns the spec with the service's default budget filled in
(``stop.max_seconds``, ``stop.max_simulations``) where the spec gives none. The operator
sets the limits with ``abcns serve`` options or ``ABCNS_*`` variables (``service.http.settings``);
``GET /limits`` and ``GET /health`` report them. The CLI on a user's own machine applies
none of them: :func:`memory_estimate` only feeds a warning there.
"""

from __future__ import annotations

from dataclasses import dataclass

from abcns import SpecError
from service.spec import Job, JobSpec, check_meaningful

POPULATIONS_ASSUMED = 200  # populations held when the spec sets no max_populations (for the estimate)


@dataclass(frozen=True)
class Limits:
    max_particles: int = 20_000
    max_batch_size: int = 10_000
    max_substeps: int = 1_000
    max_samples: int = 2**25  # samples of the observed record (and of the input); as an upload's arrays
    max_models: int = 16
    max_memory_mb: float = 2048.0  # the estimate of memory_estimate()
    max_job_seconds: float = 3600.0  # a job's wall-time budget: the default and the most a spec may ask
    max_job_simulations: int = 10**9  # a job's simulation budget: likewise

    def public(self) -> dict:
        return dict(self.__dict__)


def memory_estimate(job: Job) -> dict[str, float]:
    """Bytes a job needs at its peak, roughly: the populations the runner holds (particles x
    (widest model + 5 per-particle values) x 8 bytes, for max_populations or 200 of them,
    one for rejection: the result is read back whole at the end) and the trajectories of
    one task's batch (3 x batch_size x simulated samples x 8 bytes: the output, the state and
    the error of the numpy path; the numba path needs less; with the NMSE only the samples up
    to the end of the fit window are simulated)."""
    settings, spec = job.settings, job.spec
    width = max(m.n_dim for m in job.models) + 5
    populations = spec.stop.max_populations or (1 if spec.sampler.algorithm == "rejection" else POPULATIONS_ASSUMED)
    runner = settings.particles * width * 8 * populations
    simulated = job.observed.size
    if spec.distance.name == "nmse" and spec.data.fit is not None:
        simulated = min(simulated, spec.data.fit[1])
    worker = 3 * settings.batch_size * simulated * 8
    return {"runner": float(runner), "worker": float(worker), "total": float(runner + worker)}


def admit(spec: JobSpec, job: Job, limits: Limits) -> JobSpec:
    """The spec with the default budget filled in, or a SpecError naming the field and the limit."""

    def over(field: str, value: float, limit: float, unit: str = "", note: str = "") -> None:
        raise SpecError(field, f"{value:,.6g}{unit} exceeds this service's limit of {limit:,.6g}{unit}{note} "
                               "(ask the operator, or run it with `abcns run` on your own machine)")

    s = job.settings
    if s.particles > limits.max_particles:
        over("sampler.particles", s.particles, limits.max_particles)
    if s.batch_size > limits.max_batch_size:
        over("sampler.batch_size", s.batch_size, limits.max_batch_size)
    if len(job.models) > limits.max_models:
        over("models", len(job.models), limits.max_models, " models")
    for name, arr in (("data.observed", job.observed), ("data.input", job.force), ("data.voltage", job.voltage)):
        if arr is not None and arr.size > limits.max_samples:
            over(name, arr.size, limits.max_samples, " samples")
    for i, sim in enumerate(job.simulators):
        substeps = getattr(sim, "substeps", None)
        if substeps is not None and substeps > limits.max_substeps:
            given = spec.models[i].integrator.substeps is not None
            over(f"models[{i}].integrator.substeps", substeps, limits.max_substeps,
                 note="" if given else " (chosen from the priors' highest natural frequency: narrow the priors)")
    mb = memory_estimate(job)["total"] / 2**20
    if mb > limits.max_memory_mb:
        field = "sampler.particles" if spec.stop.max_populations else "stop.max_populations"
        over(field, round(mb), limits.max_memory_mb, " MB",
             f" of estimated memory (particles x parameters x populations: "
             f"{'fewer particles or populations' if spec.stop.max_populations else 'set stop.max_populations'})")
    pilot = getattr(s, "pilot_size", None)
    if pilot is not None and pilot > limits.max_job_simulations:
        over("sampler.pilot_size", pilot, limits.max_job_simulations, " simulations")
    stop = spec.stop
    if stop.max_seconds is not None and stop.max_seconds > limits.max_job_seconds:
        over("stop.max_seconds", stop.max_seconds, limits.max_job_seconds, " s")
    if stop.max_simulations is not None and stop.max_simulations > limits.max_job_simulations:
        over("stop.max_simulations", stop.max_simulations, limits.max_job_simulations, " simulations")
    check_meaningful(spec, job)  # a job that cannot mean anything would hold the running slot for nothing
    budget = stop.model_copy(update={
        "max_seconds": stop.max_seconds if stop.max_seconds is not None else limits.max_job_seconds,
        "max_simulations": stop.max_simulations if stop.max_simulations is not None else limits.max_job_simulations,
    })
    return spec.model_copy(update={"stop": budget})
