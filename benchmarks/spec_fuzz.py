"""Every accepted spec runs (issue M): generated specs are either refused with a field, or
run to a StopReason with finite stored results.

A hypothesis strategy varies every numeric and choice field of the sampler, the stop rules,
the distance, the seed and the priors around a small valid problem (the authors' demo
data, inline), mixing values inside the documented ranges with hostile ones (0, negative,
NaN, infinity, 1e308, 2^63, inapplicable fields). :func:`check` builds the spec as every
entry point does (``service.spec.parse`` + ``build``) and, when it is accepted, runs it in
this process into a store (``service.report.analysis.run_to_store``, serial executor) under a
small simulation budget, then checks the stored populations.

``python -m benchmarks.spec_fuzz --examples 3000 --seed 1`` prints how many specs were
refused (per field) and run (per stop reason); ``tests/test_spec_property.py`` runs a few
hundred in ``make test``.
"""

from __future__ import annotations

import argparse
import collections
import functools
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import strategies as st

from abcns import SpecError, StopReason
from service.report.analysis import run_to_store
from service.run.store import Store
from service.spec import build, parse

ROOT = Path(__file__).resolve().parent.parent
BUDGET = 3000  # simulations per run at most (every generated spec has max_simulations <= this)


@functools.cache
def _demo_data() -> tuple[tuple[float, ...], tuple[float, ...]]:
    with np.load(ROOT / "data" / "authors-demo" / "demo_data.npz") as d:
        return tuple(d["force"][:200].tolist()), tuple(d["displacement"][:200].tolist())


def base_spec() -> dict[str, Any]:
    """The authors' demo problem (linear vs cubic Duffing), 200 samples, data inline (read once)."""
    force, x = _demo_data()
    return {
        "name": "fuzz",
        "data": {"dt": 0.01, "input": list(force), "observed": list(x)},
        "models": [
            {"name": "linear", "simulator": "duffing", "fixed": {"m": 1, "k3": 0, "k5": 0},
             "priors": {"c": [0.002, 0.2], "k": [20, 80]}, "integrator": {"substeps": 1}},
            {"name": "cubic", "simulator": "duffing", "fixed": {"m": 1, "k5": 0},
             "priors": {"c": [0.002, 0.2], "k": [20, 80], "k3": [500, 1500]}, "integrator": {"substeps": 1}},
        ],
    }


HOSTILE_FLOATS = st.sampled_from([0.0, -1.0, math.nan, math.inf, -math.inf, 1e308, 1e-308, 2.0**63])
HOSTILE_INTS = st.sampled_from([0, -1, 2**31, 2**63, 10**30, 10**9])
FRACTION = st.floats(0.01, 0.99)
# the fields each algorithm reads, with values inside their documented ranges
SAMPLER = {
    "common": {
        "particles": st.integers(2, 120), "batch_size": st.integers(1, 300),
        "epsilon_initial": st.floats(1e-3, 1e3), "pilot_size": st.integers(2, 300), "pilot_quantile": FRACTION,
    },
    "abc-ns": {
        "alpha": st.floats(0.05, 0.5), "beta": st.floats(0.05, 0.5), "enlargement": st.floats(1, 10),
        "weights": st.sampled_from(["paper", "kernel"]), "variant": st.sampled_from(["evidence", "paper"]),
        "max_ellipsoids": st.integers(1, 10), "min_model_probability": st.floats(0, 0.5),
        "min_proposal_share": st.floats(0, 0.5),
    },
    "abc-smc": {"quantile": FRACTION, "schedule": st.lists(st.floats(1e-3, 200), min_size=1, max_size=4)},
    "rejection": {},
}
STOP = {
    "min_epsilon_decrease": st.floats(1e-4, 10), "epsilon_target": st.floats(1e-3, 100),
    "max_populations": st.integers(1, 6), "max_seconds": st.floats(0.5, 20),
}
# one hostile change: (section, field, values); a spec gets none or one of these
HOSTILE = [
    *(("sampler", name, HOSTILE_INTS | st.integers(-3, 1)) for name in ("particles", "batch_size", "pilot_size")),
    *(("sampler", name, HOSTILE_FLOATS) for name in (
        "epsilon_initial", "pilot_quantile", "alpha", "beta", "enlargement", "min_model_probability",
        "min_proposal_share", "quantile")),
    ("sampler", "max_ellipsoids", HOSTILE_INTS | st.just(65)),
    ("sampler", "schedule", st.lists(HOSTILE_FLOATS, min_size=0, max_size=2)),
    ("sampler", "weights", st.just("other")),
    ("sampler", "variant", st.just("other")),
    *(("stop", name, HOSTILE_FLOATS) for name in ("min_epsilon_decrease", "epsilon_target", "max_seconds")),
    *(("stop", name, HOSTILE_INTS) for name in ("max_populations", "max_simulations")),
    ("top", "seed", st.sampled_from([-1, -5, 2**63, 2**64])),
    ("distance", "summaries", st.sampled_from(["gk", "order_statistics"])),  # with nmse: does not apply
    ("prior", "k3", st.sampled_from([[1500, 500], [1000, 1000], [-1e300, 1e300], [math.nan, 1], [1, math.inf], [1]])),
]


@st.composite
def specs(draw) -> dict[str, Any]:
    """A spec inside the documented ranges, with none or one hostile change (without its
    ``data``, which :func:`check` adds: failing examples print short)."""
    spec = base_spec()
    del spec["data"]
    algorithm = draw(st.sampled_from(["abc-ns", "abc-smc", "rejection"]))
    sampler: dict[str, Any] = {"algorithm": algorithm}
    for name, values in {**SAMPLER["common"], **SAMPLER[algorithm]}.items():
        if draw(st.booleans()):  # users name few fields: each is given with probability 1/2
            sampler[name] = draw(values)
    spec["sampler"] = sampler
    stop = {name: draw(values) for name, values in STOP.items() if draw(st.booleans())}
    stop["max_simulations"] = draw(st.integers(1, BUDGET))  # always: every run is bounded
    spec["stop"] = stop
    distance = draw(st.sampled_from(["nmse", "summary_euclidean"]))
    spec["distance"] = {"name": distance}
    if distance == "summary_euclidean" and draw(st.booleans()):
        spec["distance"]["summaries"] = draw(st.sampled_from(["gk", "order_statistics"]))
    spec["seed"] = draw(st.integers(0, 2**63 - 1))
    if draw(st.booleans()):  # stiffnesses that make the integrator diverge: counted rejections, not errors
        spec["models"][1]["priors"]["k3"] = [500, 5e9]
    if draw(st.booleans()):
        section, name, values = draw(st.sampled_from(HOSTILE))
        value = draw(values)
        if section == "top":
            spec[name] = value
        elif section == "prior":
            spec["models"][1]["priors"][name] = value
        elif section == "distance":
            spec["distance"] = {"name": "nmse", "summaries": value}
        else:
            spec[section][name] = value
    return spec


def check(raw: dict[str, Any], folder: Path) -> tuple[str, str]:
    """("refused", field) or ("ran", stop reason); AssertionError on anything else (an
    internal exception propagates)."""
    raw = {"data": base_spec()["data"], **raw}
    try:
        spec = parse(raw)
        build(spec, None)
    except SpecError as err:
        if not (err.field and isinstance(err.field, str)):
            raise AssertionError(f"a SpecError without a field: {err}") from err
        return "refused", err.field.split("[")[0]
    out = folder / f"run-{time.monotonic_ns()}.zarr"
    result = run_to_store(spec, None, out)
    assert isinstance(result.stop_reason, StopReason)
    store = Store.open(out)
    assert store.attrs["status"] == "finished"
    pops = store.populations()
    assert len(pops) == len(result.populations)
    for pop in pops:
        n = pop.n_particles
        assert np.all((pop.models >= 0) & (pop.models < len(spec.models))), pop.t
        assert np.isfinite(pop.distances).all() and np.isfinite(pop.weights).all(), pop.t
        assert (pop.weights >= 0).all(), pop.t
        for i in np.unique(pop.models):  # normalised within each model (ABC-NS: 0 when all were dropped)
            total = pop.weights[pop.models == i].sum()
            assert math.isclose(total, 1.0, rel_tol=1e-9) or total == 0, (pop.t, i, total)
        assert np.isfinite(pop.model_probabilities).all(), pop.t
        for i, model in enumerate(result.models):
            rows = pop.models == i
            assert np.isfinite(pop.theta[rows, : model.n_dim]).all(), (pop.t, model.name)
        assert n == result.populations[0].n_particles
        assert not math.isnan(pop.epsilon), pop.t
        # epsilon_next is NaN only where there is none: a baseline's (the end of an SMC
        # schedule; rejection has one population)
        assert not math.isnan(pop.epsilon_next) or spec.sampler.algorithm != "abc-ns", pop.t
    return "ran", result.stop_reason.value


def main() -> None:
    from hypothesis import HealthCheck, given, settings
    from hypothesis import seed as hseed

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--examples", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    counts: collections.Counter = collections.Counter()
    start = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:

        @hseed(args.seed)
        @settings(max_examples=args.examples, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(specs())
        def run(raw):
            counts[check(raw, Path(tmp))] += 1

        run()
    total = sum(counts.values())
    print(f"{total} specs in {time.monotonic() - start:.0f} s (seed {args.seed}); nothing raised")
    for (kind, what), n in sorted(counts.items(), key=lambda kv: (kv[0][0], -kv[1])):
        print(f"  {kind:8s} {what:32s} {n:6d}")


if __name__ == "__main__":
    main()
