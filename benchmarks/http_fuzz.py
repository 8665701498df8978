"""Fuzzing the running service's two submit routes (issue R): no answer is a server error,
every refusal names its field, and every accepted job makes progress.

A seeded hypothesis run generates requests of six kinds around a small valid job (the
§4.1 Duffing data, inline, 100 particles, one population):

- ``valid``: sampler and stop fields varied inside their documented ranges;
- ``physical``: one physically invalid value: a sampling rate or interval at the ends of
  the float range, decimation, masses at or below zero, priors whose width overflows, an
  input or observed record scaled by up to 1e200 or down to 1e-200, substeps;
- ``value``: one hostile JSON value at any place of the spec (NaN, Infinity, 1e999, a
  number of 20 to 6,000 digits, a lone surrogate, a long text, null, ...);
- ``structure``: nesting 20 to 3,000 levels deep, a flat array of 10^5 to 6 x 10^6
  numbers, or a text of up to 20 MB, at any place or as the whole body;
- ``bytes``: bodies that are not JSON (cut short, not UTF-8, empty);
- ``upload``: the spec as JSON or YAML with an .npz of varied dtypes (float16 to
  longdouble, complex, integers, booleans), shapes, missing or cut-short members.

Every answer is counted by status and the field it names. Each accepted job is then
followed until it completes a population (then it is cancelled) or ends (:func:`progress`
sorts the ends); one that fails at run time or shows nothing within ``--follow-s`` made
no progress ("stuck"). The accepted specs carry ``stop.max_simulations_without_acceptance:
5000`` (NET: the safety net fires within seconds here; its default, 10^6, is
docs/design.md's); the service runs two jobs at a time with ABCNS_MAX_JOB_SECONDS=120.

    python -m benchmarks.http_fuzz [--examples 2000] [--seed 1]

starts a stock `dask scheduler` with two workers and `abcns serve`, prints the counts and
the stuck jobs, and stops everything; ``tests/test_http_holds.py`` runs a slice of it.
"""

from __future__ import annotations

import argparse
import collections
import functools
import io
import json
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import yaml
from hypothesis import strategies as st

from benchmarks.harness import AUTH, ROOT, Service, StockCluster

TERMINAL = ("finished", "failed", "cancelled")
NET = 5000  # stop.max_simulations_without_acceptance of the generated specs


@functools.cache
def _data() -> tuple[list[float], list[float]]:
    folder = ROOT / "examples" / "duffing_41"
    return np.load(folder / "force.npy").tolist(), np.load(folder / "displacement.npy").tolist()


def base_spec() -> dict[str, Any]:
    """§4.1, 1,000 samples inline, 100 particles, one population."""
    force, x = _data()
    return {
        "name": "fuzz",
        "data": {"fs": 100, "input": force, "observed": x, "fit": [0, 500], "test": [500, 1000]},
        "models": [
            {"name": "cubic", "simulator": "duffing", "fixed": {"m": 1, "k5": 0},
             "priors": {"c": [0.005, 0.5], "k": [5, 500], "k3": [100, 10000]}, "integrator": {"substeps": 4}},
            {"name": "cubic-quintic", "simulator": "duffing", "fixed": {"m": 1},
             "priors": {"c": [0.005, 0.5], "k": [5, 500], "k3": [100, 10000], "k5": [1e4, 1e6]},
             "integrator": {"substeps": 4}},
        ],
        "sampler": {"particles": 100, "batch_size": 50, "epsilon_initial": 100},
        "stop": {"max_populations": 1, "max_simulations_without_acceptance": NET},
        "seed": 1,
    }


def leaf_paths(value: Any, path: tuple = ()) -> list[tuple]:
    """Every place a value can go (two elements of a list, not all of them)."""
    out = [path]
    if isinstance(value, dict):
        for k, v in value.items():
            out += leaf_paths(v, (*path, k))
    elif isinstance(value, list):
        for i, v in enumerate(value[:2]):
            out += leaf_paths(v, (*path, i))
    return out


PATHS = leaf_paths(base_spec())
MARKER = "__FUZZ__"


def placed(spec: dict, path: tuple, raw: bytes) -> bytes:
    """The spec as JSON with the raw bytes ``raw`` at ``path`` (the whole body for ())."""
    if not path:
        return raw
    spec = json.loads(json.dumps(spec))
    node = spec
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = MARKER
    return json.dumps(spec).encode().replace(f'"{MARKER}"'.encode(), raw)


def setter(path: tuple, value: Any):
    def change(spec: dict) -> None:
        node = spec
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return change


FLOATS = [0.0, -1.0, 1e-320, 5e-324, 1e-300, 1e-100, 1e100, 1e300, 1e308, 2.0**62, -1e308]
PHYSICAL = st.one_of(
    st.sampled_from(FLOATS).map(lambda v: ("data.fs", setter(("data", "fs"), v))),
    st.sampled_from(FLOATS).map(lambda v: ("data.dt", lambda s: (s["data"].pop("fs"), s["data"].update(dt=v)))),
    st.sampled_from([0, 1, 2, 7, 1000, 1001, -1]).map(lambda q: ("data.decimate", setter(("data", "decimate"), q))),
    st.tuples(st.integers(0, 1), st.sampled_from([0.0, -1.0, 1e-300, 1e300, -0.0])).map(
        lambda a: ("fixed.m", setter(("models", a[0], "fixed", "m"), a[1]))),
    st.tuples(st.integers(0, 1), st.sampled_from([[0, 1], [-1, 1], [1e-300, 1], [-1e308, 1e308], [1, 1e308]])).map(
        lambda a: ("priors.m", lambda s: (s["models"][a[0]]["fixed"].pop("m"),
                                          s["models"][a[0]]["priors"].update(m=a[1])))),
    st.sampled_from([[-1e308, 1e308], [-1e300, 1e300], [0, 1e308], [1e307, 1.7e308]]).map(
        lambda p: ("priors.k", setter(("models", 1, "priors", "k"), p))),
    st.tuples(st.sampled_from(["input", "observed"]), st.sampled_from([2.0**62, 1e100, 1e200, 0.0, 1e-200, -1e150])).map(
        lambda a: (f"scale.{a[0]}", lambda s: s["data"].update({a[0]: [v * a[1] for v in s["data"][a[0]]]}))),
    st.sampled_from([0, 1, 1000, 1001, 10**6, 2**63]).map(
        lambda n: ("substeps", setter(("models", 0, "integrator", "substeps"), n))),
    st.sampled_from([[0, 0], [0, 1], [500, 400], [0, 1001], [-1, 10]]).map(lambda w: ("fit", setter(("data", "fit"), w))),
)
VALID = st.fixed_dictionaries({}, optional={
    "particles": st.integers(20, 200), "batch_size": st.integers(10, 200), "alpha": st.floats(0.05, 0.5),
    "beta": st.floats(0.05, 0.5), "epsilon_initial": st.floats(5, 500), "variant": st.sampled_from(["evidence", "paper"]),
})
HOSTILE_VALUES = st.one_of(
    st.sampled_from([b"NaN", b"Infinity", b"-Infinity", b"1e999", b"-1e400", b"null", b"true", b"[]", b"{}",
                     b'"\\ud800"', b'"\\u0000"', b"-0", b"1e-400", b'"' + b"x" * 100_000 + b'"']),
    st.integers(20, 6000).map(lambda n: b"9" * n),
    st.integers(20, 6000).map(lambda n: b"-1" + b"0" * n + b".5e3"),
)
STRUCTURE = st.one_of(
    st.integers(20, 3000).map(lambda d: b"[" * d + b"1" + b"]" * d),
    st.integers(20, 3000).map(lambda d: b'{"a":' * d + b"1" + b"}" * d),
    st.sampled_from([100_000, 1_000_000, 3_000_000, 6_000_000]).map(lambda n: b"[" + b",".join([b"0"] * n) + b"]"),
    st.sampled_from([1, 5, 20]).map(lambda mb: b'"' + b"a" * (mb << 20) + b'"'),
)
BYTES = st.one_of(st.binary(max_size=200), st.sampled_from([b"", b"{", b'{"name": "x"', b"\xff\xfe{}", b"\xed\xa0\x80"]))
DTYPES = ["<f8", ">f8", "<f4", "<f2", "<i8", "<i2", "|u1", "|b1", "<c16", np.dtype(np.longdouble).str]


@st.composite
def requests(draw) -> dict[str, Any]:
    """One request: {"kind", "route", "body" (bytes) or "spec" (text) + "npz" (bytes)}."""
    kind = draw(st.sampled_from(["valid", "physical", "physical", "value", "structure", "bytes", "upload"]))
    spec = base_spec()
    spec["sampler"].update(draw(VALID))
    if kind == "valid":
        return {"kind": kind, "route": "jobs", "body": json.dumps(spec).encode()}
    if kind == "physical":
        what, change = draw(PHYSICAL)
        change(spec)
        return {"kind": f"physical:{what}", "route": "jobs", "body": json.dumps(spec).encode()}
    if kind in ("value", "structure", "bytes"):
        raw = draw({"value": HOSTILE_VALUES, "structure": STRUCTURE, "bytes": BYTES}[kind])
        path = () if kind == "bytes" else draw(st.sampled_from(PATHS))
        return {"kind": kind, "route": "jobs", "body": placed(spec, path, raw)}
    # an upload: the spec's records from the .npz
    if draw(st.booleans()):
        what, change = draw(PHYSICAL)
        change(spec)
    force, x = np.asarray(spec["data"].pop("input")), np.asarray(spec["data"].pop("observed"))
    spec["data"].update(input="npz:force", observed=draw(st.sampled_from(["npz:x", "npz:x", "npz:nope", "x.npy"])))
    dtype = draw(st.sampled_from(DTYPES))
    shape = draw(st.sampled_from(["flat", "flat", "column", "matrix", "scalar"]))
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, record in (("force", force), ("x", x)):
            record = {"flat": record, "column": record[:, None], "matrix": np.vstack([record, record]),
                      "scalar": np.asarray(record[0])}[shape]
            with zf.open(f"{name}.npy", "w") as f:
                with np.errstate(all="ignore"):
                    np.lib.format.write_array(f, record.astype(dtype))
    npz = buffer.getvalue()
    if draw(st.integers(0, 9)) == 0:
        # cut short, at a share of its length: a bound drawn from the length (which varies
        # between replays of one example) made hypothesis stop with FlakyStrategyDefinition
        npz = npz[: int(len(npz) * draw(st.floats(0, 1)))]
    text = yaml.safe_dump(spec) if draw(st.booleans()) else json.dumps(spec)
    return {"kind": "upload", "route": "upload", "spec": text, "npz": npz,
            "name": draw(st.sampled_from(["spec.yaml", "spec.json", "spec"]))}


def send(http: httpx.Client, request: dict) -> httpx.Response:
    if request["route"] == "jobs":
        return http.post("/jobs", content=request["body"], headers={**AUTH, "Content-Type": "application/json"})
    return http.post("/jobs/upload", headers=AUTH, files={"spec": (request["name"], request["spec"].encode()),
                                                          "data": ("x.npz", request["npz"])})


def named(r: httpx.Response) -> str:
    """The field a refusal names ("-" for a 201, the reason for a detail without fields)."""
    if r.status_code == 201:
        return "-"
    try:
        detail = r.json()["detail"]
    except (ValueError, KeyError):
        return "(no JSON detail)"
    if isinstance(detail, list) and detail and isinstance(detail[0], dict):
        return str(detail[0].get("field") or "(no field)").split("[")[0]
    return "(text)"


def progress(http: httpx.Client, job_id: str, follow_s: float) -> str:
    """What an accepted job did: "population" (one completed: then it is cancelled), its
    own stop ("stopped:<reason>"), "accepting" (its time budget ended its first population
    after more than NET simulations: the safety net did not fire, so it had accepted
    particles), "slow" (the budget ended it before NET simulations: too slow to tell),
    "failed", or "none" (no sign within ``follow_s``)."""
    deadline = time.monotonic() + follow_s
    while time.monotonic() < deadline:
        info = http.get(f"/jobs/{job_id}", headers=AUTH).json()
        if info["status"] == "failed":
            return "failed"
        if info["status"] in TERMINAL:
            result = http.get(f"/jobs/{job_id}/result", headers=AUTH).json()
            if result.get("n_populations"):
                return "population"
            if result.get("stop_reason") not in ("max_seconds", "cancelled"):
                return f"stopped:{result.get('stop_reason')}"
            return "accepting" if (result.get("n_simulations") or 0) > NET else "slow"
        if info["progress"] is not None:
            http.delete(f"/jobs/{job_id}", headers=AUTH)
            return "population"
        time.sleep(0.1)
    http.delete(f"/jobs/{job_id}", headers=AUTH)
    return "none"


def is_stuck(outcome: str) -> bool:
    """Made no progress: failed at run time, or no sign at all within the wait."""
    return outcome in ("failed", "none")


def fuzz(url: str, examples: int, seed: int, follow_s: float = 120) -> tuple[collections.Counter, list]:
    """(answers counted by (status, kind, field), the accepted jobs that made no progress)."""
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import seed as hseed

    counts: collections.Counter = collections.Counter()
    accepted: list[tuple[str, str]] = []
    with httpx.Client(base_url=url, timeout=300) as http:

        @hseed(seed)
        @settings(max_examples=examples, deadline=None, database=None, phases=[Phase.generate],
                  suppress_health_check=list(HealthCheck))
        @given(request=requests())
        def one(request):
            r = send(http, request)
            counts[(r.status_code, request["kind"].split(":")[0], named(r))] += 1
            if r.status_code == 201:
                accepted.append((r.json()["id"], request["kind"]))

        one()
        outcomes = [(job_id, kind, progress(http, job_id, follow_s)) for job_id, kind in accepted]
    for _, kind, outcome in outcomes:
        counts[("job", kind.split(":")[0], outcome)] += 1
    return counts, [o for o in outcomes if is_stuck(o[2])]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--examples", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--follow-s", type=float, default=300)
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp())
    cluster = StockCluster(tmp / "dask")
    service = Service(tmp / "jobs", cluster.address, max_running=2,
                      env={"ABCNS_MAX_QUEUED": "5000", "ABCNS_MAX_JOB_SECONDS": "120"})
    start = time.monotonic()
    try:
        counts, stuck = fuzz(service.url, args.examples, args.seed, args.follow_s)
    finally:
        service.close()
        cluster.close()
    answers = {k: n for k, n in counts.items() if k[0] != "job"}
    by_status = collections.Counter()
    for (status, _, _), n in answers.items():
        by_status[status] += n
    print(f"{sum(answers.values())} requests in {time.monotonic() - start:.0f} s (seed {args.seed}): "
          + ", ".join(f"{n} x {s}" for s, n in sorted(by_status.items())))
    print(f"server errors (5xx): {sum(n for (s, _, _), n in answers.items() if s >= 500)}; "
          f"refusals without a field: {sum(n for (s, _, f), n in answers.items() if 400 <= s < 500 and f.startswith('('))}")
    for (status, kind, name), n in sorted(answers.items(), key=lambda kv: (kv[0][0], kv[0][1], -kv[1])):
        print(f"  {status}  {kind:10s} {name:40s} {n:6d}")
    jobs = {k: n for k, n in counts.items() if k[0] == "job"}
    print(f"accepted jobs: {sum(jobs.values())}; without progress: {len(stuck)}")
    for (_, kind, outcome), n in sorted(jobs.items()):
        print(f"  {kind:10s} {outcome:32s} {n:6d}")
    for job_id, kind, outcome in stuck:
        print(f"  stuck: {job_id} {kind} {outcome}")


if __name__ == "__main__":
    main()
