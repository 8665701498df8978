"""Digests of every population of a fixed set of serial in-process runs: the check that a
change to the engine's arithmetic (the population step, the bounds, the proposals) kept
every result bit for bit.

    python -m benchmarks.digests [--write FILE] [--compare FILE] [--only NAME,...]

Runs (serial, in this process, fixed seeds): the authors' demo in both variants; paper §4.1
(examples/duffing_41/spec.yaml) for 12 populations, evidence and paper variants; g-and-k
(paper §3.2) by ABC-SMC for 4 populations; the closed-form toys of tests/closed_form.py
(evidence variant, and the two-model toy in the paper variant) for 6 populations. Each
population prints one sha256 over all its fields; ``--write`` stores the digest of each
field (theta, distances, weights, models, survivors, epsilon, the evidence's fields, the
ellipsoids, ...), ``--compare`` lists the populations and fields that differ from a
stored file (exit status 1 when any does); each run ends with one digest of all its
populations (``all``). Digests depend on the CPU and the BLAS build (numpy's loops and
BLAS kernels round by instruction set): compare runs on the same machine, e.g. ``--write``
at the base commit, then ``--compare`` after a change. docs/benchmarks.md keeps the
``all`` digests of the project's 2-core machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from abcns import NSSettings, Population, SMCSettings, StopRules, iterate
from abcns.executor import Evaluate, SerialExecutor
from abcns.priors import Model
from abcns.run import Settings, consume
from examples.paper import authors_demo, gandk_32

ROOT = Path(__file__).resolve().parents[1]


def _sha(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a))
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def population_digests(pop: Population) -> dict[str, str]:
    """One sha256 per field of a population (timing left out)."""
    out = {
        "theta": _sha(pop.theta), "distances": _sha(pop.distances), "weights": _sha(pop.weights),
        "models": _sha(pop.models), "epsilon": _sha(np.array([pop.epsilon, pop.epsilon_next])),
        "counters": _sha(np.array([pop.n_accepted, pop.n_simulations, pop.n_failed, pop.n_redraws])),
        "model_probabilities": _sha(pop.model_probabilities),
    }
    if pop.survivors is not None:
        out["survivors"] = _sha(pop.survivors)
    if pop.held is not None:
        out["held"] = _sha(pop.held)
    if pop.ellipsoids:
        parts = []
        for bound in pop.ellipsoids:
            for e in bound:
                parts += [e.centre, e.matrix, e.axes, np.array([e.log_volume]), np.frombuffer(e.note.encode(), np.uint8)]
            parts.append(np.array([len(bound)]))
        out["ellipsoids"] = _sha(*parts)
    if pop.evidence is not None:
        for f in dataclasses.fields(pop.evidence):
            out[f"evidence.{f.name}"] = _sha(getattr(pop.evidence, f.name))
    return out


def _closed_form():
    sys.path.insert(0, str(ROOT / "tests"))
    import closed_form

    return closed_form


def _d41(variant: str) -> tuple[list[Model], Evaluate, Settings, StopRules, int]:
    from service.spec import build, load

    spec, base = load(ROOT / "examples" / "duffing_41" / "spec.yaml")
    job = build(spec, base)
    settings = dataclasses.replace(job.settings, variant=variant)
    return job.models, job.evaluate, settings, dataclasses.replace(job.stop, max_populations=12), job.seed


def _demo(variant: str) -> tuple[list[Model], Evaluate, Settings, StopRules, int]:
    p = authors_demo()
    return p.models, p.evaluate, dataclasses.replace(p.settings, variant=variant), p.stop, 1


def _gandk() -> tuple[list[Model], Evaluate, Settings, StopRules, int]:
    p = gandk_32()
    return p.models, p.evaluate, SMCSettings(particles=1000, batch_size=200), StopRules(max_populations=4), 1


def _toy(name: str, eps0: float, variant: str = "evidence") -> Callable[[], tuple]:
    def make() -> tuple[list[Model], Evaluate, Settings, StopRules, int]:
        models, evaluate = getattr(_closed_form(), name)()
        return (models, evaluate, NSSettings(particles=1000, epsilon_initial=eps0, batch_size=200, variant=variant),
                StopRules(min_epsilon_decrease=None, max_populations=6), 3)
    return make


RUNS: dict[str, Callable[[], tuple]] = {
    "demo-paper": lambda: _demo("paper"),
    "demo-evidence": lambda: _demo("evidence"),
    "d41-evidence": lambda: _d41("evidence"),
    "d41-paper": lambda: _d41("paper"),
    "gandk-smc": _gandk,
    "toy-gaussian-mean": _toy("gaussian_mean", 5.0),
    "toy-two-models": _toy("two_models", 2.0),
    "toy-two-models-paper": _toy("two_models", 2.0, "paper"),
    "toy-line-and-disc": _toy("line_and_disc", 0.3),
}


def digests(names: list[str]) -> dict[str, list[dict[str, str]]]:
    out: dict[str, list[dict[str, str]]] = {}
    for name in names:
        models, evaluate, settings, stop, seed = RUNS[name]()
        pops: list[dict[str, str]] = []
        end = consume(iterate(models, SerialExecutor(evaluate), settings, stop, seed),
                      lambda p, into=pops: into.append(population_digests(p)))
        pops.append({"end": _sha(np.array([end.n_simulations, end.n_pilot_simulations])),
                     "reason": end.reason.value})
        for t, d in enumerate(pops[:-1], 1):
            print(f"{name:22s} {t:3d} {_sha(np.frombuffer(json.dumps(d, sort_keys=True).encode(), np.uint8))[:16]}",
                  flush=True)
        print(f"{name:22s} end {pops[-1]['reason']} {pops[-1]['end'][:16]}", flush=True)
        print(f"{name:22s} all {_sha(np.frombuffer(json.dumps(pops, sort_keys=True).encode(), np.uint8))[:16]}", flush=True)
        out[name] = pops
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", type=Path, help="store the per-field digests (JSON)")
    parser.add_argument("--compare", type=Path, help="compare with stored digests; exit 1 on a difference")
    parser.add_argument("--only", default=",".join(RUNS), help="comma-separated runs (default: all)")
    args = parser.parse_args()
    names = [n for n in args.only.split(",") if n]
    got = digests(names)
    if args.write:
        args.write.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
    if args.compare:
        want = json.loads(args.compare.read_text())
        differ = False
        for name in names:
            a, b = want.get(name, []), got[name]
            if len(a) != len(b):
                print(f"DIFFER {name}: {len(b) - 1} populations, stored {len(a) - 1}")
                differ = True
            for t, (x, y) in enumerate(zip(a, b), 1):
                fields = sorted(k for k in set(x) | set(y) if x.get(k) != y.get(k))
                if fields:
                    print(f"DIFFER {name} {'end' if 'reason' in y else f'population {t}'}: {', '.join(fields)}")
                    differ = True
        print("digests differ" if differ else "digests identical")
        sys.exit(1 if differ else 0)


if __name__ == "__main__":
    main()
