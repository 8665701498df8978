"""The numba cache warmed once per run, before pytest (`make test`: ``python -m
tests.numba_warm``): the kernels the suite's jobs use on the Dask workers (the §4.1 Duffing
job and the authors' demo, which the HTTP, CLI and cluster tests run) compiled in this process
into numba's cache beside their sources (``__pycache__`` of worker/ and abcns/ in this
checkout), which every process the suite starts (Dask workers, `abcns run`, `abcns serve`)
reads. Without it, a fresh clone's first processes compile the same kernels each (a
cluster's two workers at once). On a warm cache: ~1 s."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from benchmarks.harness import ROOT, duffing_spec


def warm_specs() -> list[dict]:
    """Two populations each of the jobs the suite runs on its clusters."""
    demo = yaml.safe_load((ROOT / "examples" / "authors_demo" / "spec.yaml").read_text())
    with np.load(ROOT / "data" / "authors-demo" / "demo_data.npz") as d:
        demo["data"].update(input=d["force"].tolist(), observed=d["displacement"].tolist())
    specs = [duffing_spec(max_populations=2, particles=200), demo]
    demo["sampler"].update(particles=200, batch_size=100)
    demo["stop"] = {"min_epsilon_decrease": None, "max_populations": 2}
    return specs


def warm(folder: Path) -> None:
    """Run each of :func:`warm_specs` here, to its second population (numba compiles on first use)."""
    import worker.kernels  # noqa: F401  (first: it sets numba's CPU target before anything compiles)
    from service.run.runner import run_job
    from service.spec import parse

    for i, raw in enumerate(warm_specs()):
        run_job(parse(raw), None, folder / f"warm-{i}.zarr", None)


if __name__ == "__main__":  # `make test`: python -m tests.numba_warm, before pytest
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        warm(Path(tmp))
