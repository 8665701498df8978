"""The zarr result store: exact round trip, resume from a store, crash-safe appends,
xarray while a job runs, attributes and errors."""

import contextlib
import hashlib
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import zarr
from zarr.core.array import AsyncArray

import abcns
import service.run.store.metadata as store_metadata
from abcns import NSSettings, Population, SerialExecutor, StopReason, StopRules
from abcns import ellipsoid as ell
from abcns.evidence import Evidence
from abcns.filling import Budget
from abcns.noise import Floor
from benchmarks.harness import wait_until
from service.run.store import (
    FORMAT_VERSION,
    NOTE_CODES,
    PARTIAL_WARNING,
    SCHEMA,
    Store,
    StoreError,
    StoreNotFound,
    data_hash,
    dataset_result,
    model_view,
    result_from_store,
)
from tests.closed_form import line_and_disc, two_models

SETTINGS = NSSettings(particles=200, epsilon_initial=2.0, batch_size=50)
SEED = 3
SPEC = {"name": "two-models", "sampler": {"particles": 200, "epsilon_initial": 2.0, "batch_size": 50}, "seed": SEED}
ARRAYS = ("models", "theta", "distances", "weights", "survivors", "held", "model_probabilities",
          "n_simulations_by_model", "n_failed_by_model")
SCALARS = ("t", "epsilon", "epsilon_next", "n_accepted", "n_simulations", "n_failed", "n_redraws")


def stop_after(n: int) -> StopRules:
    return StopRules(min_epsilon_decrease=None, max_populations=n)


def new_store(path: Path, models, n_particles: int = 200, **kw) -> Store:
    args = dict(spec=SPEC, seed=SEED, model_names=[m.name for m in models],
                parameter_names=[list(m.parameter_names) for m in models], n_particles=n_particles,
                data_hash=data_hash(np.array([0.5])), algorithm="abc-ns")
    return Store.create(path, **{"max_ellipsoids": SETTINGS.n_ellipsoids, **args, **kw})


def run_into(store: Store, n_populations: int) -> tuple[list[Population], list[int]]:
    """A real in-process run appending each population; (populations, cumulative simulations)."""
    models, evaluate = two_models()
    stop = stop_after(n_populations)
    budget = Budget(stop)
    pops, totals = [], []

    def on_population(pop: Population) -> None:
        pops.append(pop)
        totals.append(budget.n_simulations)
        store.append(pop, n_simulations_total=budget.n_simulations)

    result = abcns.run(models, evaluate, SETTINGS, stop, seed=SEED, on_population=on_population, budget=budget)
    assert result.stop_reason is StopReason.MAX_POPULATIONS and len(pops) == n_populations
    assert totals[-1] == result.n_simulations
    return pops, totals


def same_bits(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def assert_same_population(a: Population, b: Population, *, elapsed: bool = True) -> None:
    for name in ARRAYS:
        assert same_bits(getattr(a, name), getattr(b, name)), f"population {a.t}: {name}"
    for name in SCALARS + (("elapsed_s",) if elapsed else ()):
        x, y = getattr(a, name), getattr(b, name)
        assert type(x) is type(y) and x == y, f"population {a.t}: {name} {x!r} != {y!r}"
    assert len(a.ellipsoids) == len(b.ellipsoids)
    for i, (u, v) in enumerate(zip(a.ellipsoids, b.ellipsoids)):
        assert len(u) == len(v), f"population {a.t}: bound of model {i}"
        for e, f in zip(u, v):
            for name in ("centre", "matrix", "axes"):
                assert same_bits(getattr(e, name), getattr(f, name)), f"population {a.t}: ellipsoid {i} {name}"
            assert e.log_volume == f.log_volume and e.note == f.note
    assert (a.evidence is None) == (b.evidence is None)
    if a.evidence is not None:
        for name in a.evidence.FLOATS + a.evidence.INTS:
            x, y = getattr(a.evidence, name), getattr(b.evidence, name)
            assert np.array_equal(x, y, equal_nan=True) and x.dtype == y.dtype, f"population {a.t}: evidence.{name}"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """Store A: five populations of a real run, and the in-memory records."""
    models, _ = two_models()
    store = new_store(tmp_path_factory.mktemp("a") / "job.zarr", models)
    pops, totals = run_into(store, 5)
    return store, pops, totals


def test_round_trip_is_bit_identical(reference):
    store, pops, totals = reference
    assert store.n_populations == 5
    back = Store.open(store.path).populations()
    assert len(back) == 5
    for a, b in zip(pops, back):
        assert_same_population(a, b)
    assert all(len(p.ellipsoids) == 2 for p in back) and all(p.survivors is not None for p in back)
    assert_same_population(store.population(3), pops[2])
    for t in (0, 6):
        with pytest.raises(IndexError, match=r"holds populations 1\.\.5"):
            store.population(t)
    g = zarr.open_group(str(store.path), mode="r")
    assert g["n_simulations_total"][:].tolist() == totals
    assert store.totals().tolist() == totals
    assert store.run_state() == {"n_populations": 5, "t": 5, "n_simulations_total": totals[-1],
                                 "elapsed_s": pops[-1].elapsed_s}


def test_resume_from_store_equals_uninterrupted_run(reference, tmp_path):
    store_a, _pops_a, totals_a = reference
    models, evaluate = two_models()
    run_into(new_store(tmp_path / "b.zarr", models), 2)

    store_b = Store.open(tmp_path / "b.zarr")
    history = store_b.populations()
    state = store_b.run_state()
    assert state["n_populations"] == 2 and state["n_simulations_total"] == totals_a[1]
    stop = stop_after(5)
    budget = Budget(stop, n_simulations=state["n_simulations_total"], elapsed_before_s=state["elapsed_s"])
    gen = abcns.abc_ns(models, SerialExecutor(evaluate), SETTINGS, stop, SEED, history=history, budget=budget)
    while True:
        try:
            pop = next(gen)
        except StopIteration as done:
            end = done.value
            break
        store_b.append(pop, n_simulations_total=budget.n_simulations)
    assert end.reason is StopReason.MAX_POPULATIONS

    assert store_b.n_populations == 5
    for a, b in zip(store_a.populations(), store_b.populations()):
        assert_same_population(a, b, elapsed=False)
    g = zarr.open_group(str(store_b.path), mode="r")
    assert g["n_simulations_total"][:].tolist() == totals_a


def assert_same_arrays(path_a: Path, path_b: Path) -> None:
    """Every array of two stores equal (shape, dtype, values; NaN equal to NaN)."""
    a, b = zarr.open_group(str(path_a), mode="r"), zarr.open_group(str(path_b), mode="r")
    names = sorted(k for k, _ in a.arrays())
    assert names == sorted(k for k, _ in b.arrays())
    for name in names:
        x, y = np.asarray(a[name][...]), np.asarray(b[name][...])
        assert x.dtype == y.dtype and x.shape == y.shape, name
        if x.dtype.kind == "f":
            assert x.tobytes() == y.tobytes(), name
        else:
            assert np.array_equal(x, y), name


class Crash(Exception):
    pass


def test_crash_before_counter_leaves_a_store_that_reads_and_appends_cleanly(reference, tmp_path, monkeypatch):
    store_a, pops, totals = reference
    models, _ = two_models()
    store = new_store(tmp_path / "c.zarr", models)
    for pop, total in zip(pops[:2], totals[:2]):
        store.append(pop, n_simulations_total=total)

    def crash(self, n):
        raise Crash

    with monkeypatch.context() as m:  # every array written, counter not bumped
        m.setattr(Store, "_commit", crash)
        with pytest.raises(Crash):
            store.append(pops[2], n_simulations_total=totals[2])
    reopened = Store.open(store.path)
    assert reopened.n_populations == 2
    assert xr.open_zarr(store.path, consolidated=False).sizes["population"] == 3  # the extra row is there
    assert reopened.dataset().sizes["population"] == 2  # and hidden by the counter
    assert len(reopened.populations()) == 2 and reopened.run_state()["n_simulations_total"] == totals[1]
    assert reopened.totals().tolist() == totals[:2]  # the counter hides the extra row here too
    for a, b in zip(pops, reopened.populations()):
        assert_same_population(a, b)

    # a second crash half-way through the arrays of the next attempt (some resized, some not)
    calls = {"n": 0}
    setitem = AsyncArray.setitem

    async def flaky(self, key, value, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 4:
            raise Crash
        await setitem(self, key, value, *args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(AsyncArray, "setitem", flaky)
        with pytest.raises(Crash):
            reopened.append(replace(pops[3], t=3), n_simulations_total=-5)
    assert Store.open(store.path).n_populations == 2

    reopened = Store.open(store.path)
    for pop, total in zip(pops[2:], totals[2:]):
        reopened.append(pop, n_simulations_total=total)
    assert reopened.n_populations == 5
    for a, b in zip(store_a.populations(), reopened.populations()):
        assert_same_population(a, b)
    assert_same_arrays(store_a.path, reopened.path)


def test_xarray_reads_the_store_between_appends(reference, tmp_path):
    _, pops, totals = reference
    models, _ = two_models()
    store = new_store(tmp_path / "x.zarr", models)
    ds = xr.open_zarr(store.path, consolidated=False)
    assert ds.sizes["population"] == 0 and ds["theta"].dims == ("population", "particle", "parameter")
    for pop, total in zip(pops, totals):
        store.append(pop, n_simulations_total=total)
        ds = xr.open_zarr(store.path, consolidated=False)
        assert dict(ds.sizes) == {"population": pop.t, "particle": 200, "model": 2, "ellipsoid": SETTINGS.n_ellipsoids,
                                  "parameter": 1, "parameter_b": 1}
        assert ds["population"].values.tolist() == list(range(1, pop.t + 1))
        assert ds["model"].values.tolist() == ["narrow", "wide"] and ds["parameter"].values.tolist() == ["theta"]
        assert ds["model_index"].dims == ("population", "particle") and ds["model_index"].dtype == np.int16
        assert ds["ellipsoid_matrix"].dims == ("population", "model", "ellipsoid", "parameter", "parameter_b")
        assert ds["model_probability"].dims == ("population", "model")
        assert ds["epsilon"].dims == ("population",)
        assert store.dataset().identical(ds)
        row = ds.sel(population=pop.t)
        assert same_bits(row["model_index"].values, pop.models)
        assert same_bits(row["theta"].values, pop.theta)
        assert same_bits(row["distance"].values, pop.distances)
        assert same_bits(row["weight"].values, pop.weights)
        assert same_bits(row["survivor"].values, pop.survivors)
        assert same_bits(row["model_probability"].values, pop.model_probabilities)
        assert float(row["epsilon"]) == pop.epsilon and float(row["epsilon_next"]) == pop.epsilon_next
        assert float(row["acceptance_rate"]) == pop.acceptance_rate
        assert int(row["n_simulations"]) == pop.n_simulations and int(row["n_failed"]) == pop.n_failed
        assert int(row["n_simulations_total"]) == total
        for i, bound in enumerate(pop.ellipsoids):
            for j, e in enumerate(bound):
                assert same_bits(row["ellipsoid_centre"].values[i, j], e.centre)
                assert same_bits(row["ellipsoid_matrix"].values[i, j], e.matrix)
                assert int(row["ellipsoid_note"].values[i, j]) == NOTE_CODES[e.note]


def synthetic(t: int, *, baseline: bool = False) -> Population:
    """Two models of 1 and 3 parameters, a dead model, every ellipsoid note."""
    rng = np.random.default_rng(t)
    n = 6
    models = np.array([1, 1, 1, 1, 1, 1], dtype=np.int16)
    theta = np.full((n, 3), np.nan)
    theta[:, :3] = rng.random((n, 3))
    box = ell.from_box(np.zeros(3), np.ones(3))
    notes = ["", "repaired", "fallback", "box"]
    e = ell.from_matrix(rng.random(3), box.matrix * (1 + t), notes[t % 4])
    return Population(
        t=t, epsilon=float(np.inf) if t == 1 else 1.0 / t, epsilon_next=0.5 / t, models=models, theta=theta,
        distances=rng.random(n), weights=np.full(n, 1 / n), n_accepted=n, n_simulations=10 * t, n_failed=t,
        n_redraws=2 * t, elapsed_s=0.1 * t,
        survivors=None if baseline else rng.random(n) < 0.5,
        ellipsoids=() if baseline else ((), (e,)),
        model_probabilities=np.array([0.0, 1.0]),
    )


def test_mixed_dimensions_dead_models_notes_and_baseline_records(tmp_path):
    models = [abcns.Model("one", {"a": (0, 1)}), abcns.Model("three", {"x": (0, 1), "y": (0, 1), "z": (0, 1)})]
    store = new_store(tmp_path / "m.zarr", models, n_particles=6, algorithm="abc-smc")
    pops = [synthetic(1, baseline=True)] + [synthetic(t) for t in range(2, 6)]
    for pop in pops:
        store.append(pop, n_simulations_total=10 * pop.t)
    back = Store.open(store.path).populations()
    for a, b in zip(pops, back):
        assert_same_population(a, b)
    assert back[0].survivors is None and back[0].ellipsoids == ()
    assert {b.ellipsoids[1][0].note for b in back[1:]} == {"", "repaired", "fallback", "box"}
    ds = xr.open_zarr(store.path, consolidated=False)
    assert ds["parameter"].values.tolist() == ["a", "x", "y", "z"]
    assert ds["model_has_parameter"].values.tolist() == [[True, False, False, False], [False, True, True, True]]
    for pop, row in zip(pops, ds["theta"].values):  # model "three"'s x, y, z in their named columns
        assert np.isnan(row[:, 0]).all() and same_bits(row[:, 1:], pop.theta)
    assert np.isnan(ds["ellipsoid_matrix"].values[:, 0]).all()  # the dead model
    assert ds["ellipsoid_note"].values[:, 0].tolist() == [[-1] * SETTINGS.n_ellipsoids] * 5


def test_append_refuses_wrong_order_and_shapes(tmp_path):
    models = [abcns.Model("one", {"a": (0, 1)}), abcns.Model("three", {"x": (0, 1), "y": (0, 1), "z": (0, 1)})]
    store = new_store(tmp_path / "w.zarr", models, n_particles=6)
    with pytest.raises(StoreError, match="population 2 cannot follow population 0"):
        store.append(synthetic(2), n_simulations_total=1)
    with pytest.raises(StoreError, match="theta has shape"):
        store.append(replace(synthetic(1), theta=np.zeros((6, 2))), n_simulations_total=1)
    assert store.n_populations == 0
    assert xr.open_zarr(store.path, consolidated=False).sizes["population"] == 0  # nothing written


def test_attributes_status_and_format_version(reference):
    store = Store.open(reference[0].path)
    attrs = store.attrs
    assert attrs["format_version"] == FORMAT_VERSION == 7
    assert attrs["spec"] == SPEC and attrs["seed"] == SEED and attrs["algorithm"] == "abc-ns"
    assert attrs["data_hash"] == data_hash(np.array([0.5]))
    assert attrs["model_names"] == ["narrow", "wide"] and attrs["parameter_names"] == [["theta"], ["theta"]]
    assert {"abcns", "numpy", "scipy", "zarr", "xarray", "python", "numba", "dask", "distributed"} <= set(attrs["versions"])
    assert attrs["versions"]["zarr"] == zarr.__version__
    assert attrs["status"] == "running" and attrs["stop_reason"] is None and attrs["n_populations"] == 5

    store.set_status("finished", StopReason.MAX_POPULATIONS, n_simulations=1234, n_pilot_simulations=0,
                     epsilon_initial_source="given", wall_time_s=1.5, notes=["a note"])
    attrs = Store.open(store.path).attrs
    assert attrs["status"] == "finished" and attrs["stop_reason"] == "max_populations"
    assert attrs["n_simulations"] == 1234 and attrs["notes"] == ["a note"] and attrs["wall_time_s"] == 1.5
    assert attrs["spec"] == SPEC and attrs["n_populations"] == 5
    with pytest.raises(ValueError, match="status must be one of"):
        store.set_status("done")
    with pytest.raises(ValueError, match="reserved"):
        store.set_status("failed", n_populations=3)
    with pytest.raises(StoreError, match="JSON-able"):
        store.set_status("failed", notes=[object()])
    assert store.attrs["status"] == "finished"


def test_a_status_change_is_one_write_so_a_kill_leaves_the_old_or_the_new(tmp_path, monkeypatch):
    """CI's chaos run: the service was SIGKILLed inside set_status("finished", ...) and the
    store said "finished" with no stop reason and the run information of population 1: zarr's
    ``attrs.update`` rewrites the group's metadata once per key, and the kill came between
    the first key (status) and the next. A status change is one write of the metadata now.
    Here the process "dies" at the second write of the group's metadata (zarr.json)."""
    models, _ = two_models()
    store = new_store(tmp_path / "s.zarr", models)
    store.set_status("running", None, run={"epsilon_initial_source": "given"})
    writes: list[str] = []
    write, store_set = store_metadata.replace, zarr.storage.LocalStore.set

    def dies_at_the_second_write(file, data):
        if file.name == "zarr.json" and file.parent == store.path:
            writes.append(file.name)
            if len(writes) > 1:
                raise Crash("killed")
        write(file, data)

    async def zarr_writes(self, key, value):  # the group's metadata is not written through zarr
        writes.append(f"zarr: {key}")
        await store_set(self, key, value)

    with monkeypatch.context() as m, contextlib.suppress(Crash):
        m.setattr(store_metadata, "replace", dies_at_the_second_write)
        m.setattr(zarr.storage.LocalStore, "set", zarr_writes)
        store.set_status("finished", StopReason.MAX_POPULATIONS, run={"epsilon_initial_source": "given", "n_simulations": 12})
    a = Store.open(store.path).attrs
    assert (a["status"], a["stop_reason"], a["run"]) in (
        ("running", None, {"epsilon_initial_source": "given"}),  # the old attributes
        ("finished", "max_populations", {"epsilon_initial_source": "given", "n_simulations": 12}),  # or the new
    ), (a["status"], a["stop_reason"], a["run"])
    assert writes == ["zarr.json"]  # one write


def test_open_and_create_errors(tmp_path):
    with pytest.raises(StoreNotFound, match="does not exist"):
        Store.open(tmp_path / "missing.zarr")
    (tmp_path / "empty").mkdir()
    with pytest.raises(StoreError, match="not a result store"):
        Store.open(tmp_path / "empty")
    zarr.open_group(str(tmp_path / "plain.zarr"), mode="w", zarr_format=3).attrs["x"] = 1
    with pytest.raises(StoreError, match=r"not a result store .no format_version"):
        Store.open(tmp_path / "plain.zarr")

    models, _ = two_models()
    store = new_store(tmp_path / "empty", models)  # an empty directory is fine
    zarr.open_group(str(store.path), mode="r+").attrs["format_version"] = 1
    with pytest.raises(StoreError, match="format_version 1; this abcns reads version 7"):
        Store.open(store.path)

    with pytest.raises(StoreError, match="already exists"):
        new_store(store.path, models)
    (tmp_path / "file").write_text("x")
    with pytest.raises(StoreError, match="already exists"):
        new_store(tmp_path / "file", models)
    assert (tmp_path / "file").read_text() == "x"
    with pytest.raises(StoreError, match="spec must be JSON-able"):
        new_store(tmp_path / "bad.zarr", models, spec={"x": float("nan")})
    assert not (tmp_path / "bad.zarr").exists()


def test_data_hash():
    x = np.arange(6, dtype=float)
    h = data_hash(x, np.ones(2))
    assert h.startswith("sha256:") and h == data_hash(x.copy(), np.ones(2))
    assert h != data_hash(np.ones(2), x)
    assert data_hash(x) != data_hash(x.reshape(2, 3))
    assert data_hash(x) != data_hash(x.astype(np.float32))
    # the same bytes and shape under another dtype (zeros; a view; the other byte order's
    # bytes): only the dtype in the hash tells them apart
    assert data_hash(np.zeros(3)) != data_hash(np.zeros(3, dtype=np.int64))
    assert data_hash(x) != data_hash(x.view(np.int64))
    assert data_hash(x) != data_hash(x.byteswap().view(x.dtype.newbyteorder()))
    assert data_hash(x) != data_hash(x + 1e-12)
    assert data_hash(x[::2]) == data_hash(np.ascontiguousarray(x[::2]))
    with pytest.raises(TypeError):
        data_hash(np.array([None]))


# Run by another Python process: read-modify-writes of the attributes as fast as it can
# (set_status with a counter of its own, ``progress``) until told to stop, checking before
# each one that its previous write and the appender's counter are still there.
UPDATER = """
import json, sys
from pathlib import Path
from service.run.store import Store
store, stop = Store.open(sys.argv[1]), Path(sys.argv[2])
lost, i, last_n = [], 0, 0
while not stop.exists():
    attrs = store.attrs
    if attrs.get("progress", 0) != i:
        lost.append(["progress", i, attrs.get("progress")])
    if attrs["n_populations"] < last_n:
        lost.append(["n_populations", last_n, attrs["n_populations"]])
    last_n = attrs["n_populations"]
    i += 1
    store.set_status("cancelled", stop_reason="cancelled", progress=i)
print(json.dumps({"updates": i, "lost": lost}))
"""


def test_status_set_by_another_process_during_appends_is_kept(reference, tmp_path):
    """The scheduler's process sets the status while the runner's appends bump the counter:
    with the flock in store_metadata.update_attrs neither read-modify-write loses the other's update.
    Measured with the flock made a no-op: in 10 runs of 10 a write of the other process from
    a stale read wiped the counter within the first 1-7 appends (and in 2 the other process
    saw its own ``progress`` overwritten); with the lock, 40 appends meet ~300 updates in
    ~6 s on 2 cores, so a pass without the lock is practically impossible."""
    _, pops, totals = reference
    models, _ = two_models()
    writer = new_store(tmp_path / "s.zarr", models)
    stop = tmp_path / "stop"
    root = Path(__file__).resolve().parents[1]
    other = subprocess.Popen([sys.executable, "-c", UPDATER, str(writer.path), str(stop)], cwd=root,
                             env={**os.environ, "PYTHONPATH": str(root)}, stdout=subprocess.PIPE, text=True)
    appended, errors = 0, []
    try:
        deadline = time.monotonic() + 60
        while "progress" not in writer.attrs:  # the other process is up and writing
            assert other.poll() is None and time.monotonic() < deadline, "the updater did not start"
            time.sleep(0.01)
        for k in range(1, 41):
            try:
                writer.append(replace(pops[(k - 1) % 5], t=k), n_simulations_total=totals[-1] * k)
                appended += 1
            except StoreError as err:  # our counter was overwritten: "population t cannot follow ..."
                errors.append(str(err))
                break
    finally:
        stop.touch()
        out, _ = other.communicate(timeout=60)
    assert other.returncode == 0
    report = json.loads(out)
    assert not errors, errors
    assert not report["lost"], report["lost"][:5]
    attrs = Store.open(writer.path).attrs
    assert report["updates"] > appended == attrs["n_populations"] == 40  # the updates interleaved with the appends
    assert attrs["progress"] == report["updates"] and attrs["status"] == "cancelled"
    assert xr.open_zarr(writer.path, consolidated=False).sizes["population"] == 40


def test_a_reader_polling_during_appends_sees_only_complete_populations(reference, tmp_path):
    """Quiet too (filterwarnings = error): Store.dataset ignores zarr's warning about the
    temporary files of an attribute update it may list."""
    _, pops, totals = reference
    models, _ = two_models()
    store = new_store(tmp_path / "r.zarr", models)
    seen, errors, done = [], [], threading.Event()

    def poll():
        reader = Store.open(store.path)
        while not done.is_set():
            try:
                ds = reader.dataset()
                n = ds.sizes["population"]
                assert ds["population"].values.tolist() == list(range(1, n + 1))
                assert not np.isnan(ds["distance"].values).any() and (ds["model_index"].values >= 0).all()
                assert (ds["n_simulations_total"].values == totals[:n]).all()
                seen.append(n)
            except Exception as err:  # reported below
                errors.append(err)
                return

    thread = threading.Thread(target=poll)
    thread.start()
    try:
        for k, (pop, total) in enumerate(zip(pops, totals), start=1):
            store.append(pop, n_simulations_total=total)
            # the reader sees this population before the next append (it polls all along)
            wait_until(lambda: errors or (seen and seen[-1] >= k), 60, f"the reader to see population {k}", 0.005)
    finally:
        done.set()
        thread.join()
    assert not errors, errors
    assert seen == sorted(seen) and seen[-1] == 5


def test_the_store_is_self_describing_for_xarray(tmp_path):
    """I.11: names along model and parameter (``sel`` by name), attributes with units, and
    ``to_netcdf`` of the store as xarray opens it."""
    models = [abcns.Model("one", {"a": (0, 1)}), abcns.Model("three", {"x": (0, 1), "y": (0, 1), "z": (0, 1)})]
    store = new_store(tmp_path / "s.zarr", models, n_particles=6)
    pops = [synthetic(t) for t in range(1, 4)]
    for pop in pops:
        store.append(pop, n_simulations_total=10 * pop.t)
    ds = xr.open_zarr(store.path, consolidated=False)
    assert ds.indexes["model"].tolist() == ["one", "three"] and ds.indexes["parameter"].tolist() == ["a", "x", "y", "z"]
    y = ds["theta"].sel(population=2, parameter="y").values  # every particle is model "three"'s
    assert same_bits(y, pops[1].theta[:, 1])
    centre = ds["ellipsoid_centre"].sel(model="three", parameter="z").isel(ellipsoid=0).values
    assert same_bits(centre, np.array([p.ellipsoids[1][0].centre[2] for p in pops]))
    assert np.isnan(ds["ellipsoid_centre"].sel(model="three", parameter="a").values).all()
    assert same_bits(ds["model_probability"].sel(model="three").values, np.ones(3))
    for name, var in ds.variables.items():
        assert var.attrs.get("long_name") and var.attrs.get("description"), name
    assert ds["epsilon"].attrs["units"] == ds["distance"].attrs["units"] == "%"  # the spec's NMSE (Eq. 7 is in percent)
    assert ds["elapsed_s"].attrs["units"] == "s"
    assert json.loads(ds.attrs["spec"].removeprefix("json:")) == SPEC and Store.open(store.path).attrs["spec"] == SPEC
    nc = tmp_path / "s.nc"
    ds.to_netcdf(nc)
    back = xr.open_dataset(nc)
    assert same_bits(back["theta"].values, ds["theta"].values)
    assert back.indexes["parameter"].tolist() == ["a", "x", "y", "z"]
    assert json.loads(back.attrs["versions"].removeprefix("json:"))["abcns"] == abcns.__version__


def test_a_store_whose_creation_was_cut_is_made_again_only_where_the_caller_owns_it(tmp_path):
    """A process killed inside Store.create leaves a zarr group without format_version (CI's
    chaos run met it: the service SIGKILLed while it created a job's store). The service,
    whose job folder owns the path, makes the store again and runs the job; `abcns run
    --out` (not owned) refuses it and deletes nothing."""
    from service.run.runner import run_job
    from service.run.store import StoreIncomplete
    from service.spec import parse

    demo = Path(__file__).resolve().parents[1] / "data" / "authors-demo" / "demo_data.npz"
    raw = {"name": "cut", "data": {"dt": 0.01, "input": f"{demo}:force", "observed": f"{demo}:displacement"},
           "models": [{"name": "linear", "simulator": "duffing", "fixed": {"m": 1, "k3": 0, "k5": 0},
                       "priors": {"c": [0.002, 0.2], "k": [20, 80]}, "integrator": {"substeps": 1}}],
           "sampler": {"particles": 50, "batch_size": 25, "epsilon_initial": 100}, "stop": {"max_populations": 2}}
    spec = parse(raw)
    for owned in (False, True):
        path = tmp_path / f"owned-{owned}.zarr"
        zarr.open_group(str(path), mode="w-", zarr_format=3).attrs.update({"spec": "json:{}"})  # cut before the end
        if not owned:
            with pytest.raises(StoreIncomplete, match="creation did not finish"):
                run_job(spec, Path("/"), path, None)
            assert (path / "zarr.json").exists()
        else:
            result = run_job(spec, Path("/"), path, None, owned_store=True)
            assert len(result.populations) == 2 and Store.open(path).n_populations == 2



def linear_demo_raw(name: str) -> dict:
    """A two-population job of the authors' linear model on their demo data (50 particles)."""
    demo = Path(__file__).resolve().parents[1] / "data" / "authors-demo" / "demo_data.npz"
    return {"name": name, "data": {"dt": 0.01, "input": f"{demo}:force", "observed": f"{demo}:displacement"},
            "models": [{"name": "linear", "simulator": "duffing", "fixed": {"m": 1, "k3": 0, "k5": 0},
                        "priors": {"c": [0.002, 0.2], "k": [20, 80]}, "integrator": {"substeps": 1}}],
            "sampler": {"particles": 50, "batch_size": 25, "epsilon_initial": 100}, "stop": {"max_populations": 2}}

def test_a_store_an_earlier_version_made_for_the_job_is_this_jobs(tmp_path):
    """Its job key hashed that version's dump of the spec (the flat sampler section, nulls
    for the fields of other algorithms); the spec it holds validates to this job's, so
    run_job takes it as this job's store (here: finished, so its result) instead of
    calling it another job's."""
    import hashlib

    from service.run.runner import run_job
    from service.spec import parse

    raw = linear_demo_raw("old")
    spec, path = parse(raw), tmp_path / "old.zarr"
    first = run_job(spec, Path("/"), path, None)
    store = Store.open(path)
    old = spec.model_dump(mode="json")
    old["sampler"] = {**{name: None for name in ("alpha", "beta", "enlargement", "weights", "variant", "max_ellipsoids",
                                                 "min_model_probability", "min_proposal_share", "quantile",
                                                 "schedule", "pilot_size")},
                      **raw["sampler"], "algorithm": "abc-ns", "pilot_quantile": 0.5}
    a = store.attrs
    old_key = hashlib.sha256(json.dumps({"spec": old, "seed": a["seed"], "data": a["data_hash"]},
                                        sort_keys=True).encode()).hexdigest()
    store_metadata.update_attrs(store.path, {"spec": old, "job_key": old_key})
    again = run_job(spec, Path("/"), path, None)
    assert len(again.populations) == 2 and same_bits(again.populations[1].theta, first.populations[1].theta)
    with pytest.raises(abcns.SpecError, match="holds another job"):
        run_job(parse({**raw, "seed": 5}), Path("/"), path, None)


def test_a_store_marked_finished_without_a_stop_reason_is_resumed_not_called_cancelled(tmp_path):
    """What a service killed inside set_status("finished", ...) left while a status change was
    one write per key: the store "finished", no stop reason, the run information of
    population 1. run_job returned it as the job's result, with the stop reason "cancelled"
    (result_of's word for a run that has none), and the service ended the job cancelled (CI's
    chaos run). Such a store is resumed: the run ends at once (its populations are all
    there) and records why, as the uninterrupted run did."""
    from service.run.runner import run_job
    from service.spec import parse

    raw = linear_demo_raw("torn")
    spec, path = parse(raw), tmp_path / "torn.zarr"
    first = run_job(spec, Path("/"), path, None)
    store = Store.open(path)
    run = {k: store.attrs["run"][k] for k in ("epsilon_initial_source", "n_pilot_simulations")}  # population 1's
    store_metadata.update_attrs(store.path, {"status": "finished", "stop_reason": None, "run": run})
    again = run_job(spec, Path("/"), path, None)
    assert again.stop_reason is first.stop_reason is StopReason.MAX_POPULATIONS
    a = Store.open(path).attrs
    assert (a["status"], a["stop_reason"], a["run"]["n_simulations"]) == ("finished", "max_populations", first.n_simulations)
    assert len(again.populations) == 2 and same_bits(again.populations[1].theta, first.populations[1].theta)


def test_zarrs_warning_about_a_half_written_metadata_file_is_ignored_by_dataset_only(tmp_path):
    """zarr writes each metadata file through a temporary ``zarr.<uuid>.partial``; a reader
    listing the group meanwhile (xarray.open_zarr) meets it and warns. Store.dataset ignores
    that warning (filterwarnings = error here); importing the store leaves the process's
    warning filters alone, so xarray.open_zarr elsewhere still warns."""
    models = [abcns.Model("one", {"a": (0, 1)}), abcns.Model("three", {"x": (0, 1), "y": (0, 1), "z": (0, 1)})]
    store = new_store(tmp_path / "p.zarr", models, n_particles=6)
    store.append(synthetic(1), n_simulations_total=10)
    (store.path / "zarr.0123abcd.partial").write_text("{}")  # an attribute update under way
    assert store.dataset().sizes["population"] == 1
    with pytest.warns(zarr.errors.ZarrUserWarning, match=PARTIAL_WARNING):
        xr.open_zarr(store.path, consolidated=False)
    code = ("import warnings, service.run.store as s; "
            "print(any(getattr(f[1], 'pattern', None) == s.PARTIAL_WARNING for f in warnings.filters))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.stdout.strip() == "False", done.stdout + done.stderr


# ---------------------------------------------------------------- P.7, Q.13: geometry, xarray, per-model views
def line_and_disc_store(path: Path, variant: str, n_populations: int = 4, log: bool = False) -> Store:
    """A real run of tests.closed_form.line_and_disc (models of 1 and 2 parameters on the unit
    box, shifted and scaled so the unit prior box and the parameters differ), appended
    population by population, with the spec the runner stores (its models and sampler).
    ``log``: every prior log-uniform (boxes [2, 7] and [0.5, 60.5]), the distances those of
    log theta's unit box."""
    models, evaluate = line_and_disc()
    low, width = np.array([2.0, 0.5 if log else -30.0]), np.array([5.0, 60.0])  # prior boxes [2, 7] and [-30, 30]
    models = [abcns.Model(m.name, {p: (low[j], low[j] + width[j], "log") if log else (low[j], low[j] + width[j])
                                   for j, p in enumerate(m.parameter_names)}) for m in models]
    inner = evaluate

    def evaluate_raw(batch):  # the closed-form distances on the unit box
        d = batch.theta.shape[1]
        if log:
            unit = np.log(batch.theta / low[:d]) / np.log1p(width[:d] / low[:d])
        else:
            unit = (batch.theta - low[:d]) / width[:d]
        return inner(replace(batch, theta=unit))

    settings = NSSettings(particles=300, epsilon_initial=0.5, batch_size=100, variant=variant)
    spec = {"models": [m.config_dict() for m in models], "sampler": {"variant": variant, "particles": 300}}
    store = Store.create(path, spec=spec, seed=1, model_names=[m.name for m in models],
                         parameter_names=[list(m.parameter_names) for m in models], n_particles=300, data_hash="",
                         algorithm="abc-ns", max_ellipsoids=settings.n_ellipsoids)
    abcns.run(models, evaluate_raw, settings, stop_after(n_populations), seed=1,
              on_population=lambda pop: store.append(pop, n_simulations_total=0))
    return store


@pytest.mark.parametrize("log", [False, True], ids=["uniform", "log-uniform"])
@pytest.mark.parametrize("variant", ["evidence", "paper"])
def test_the_ellipsoids_are_what_their_description_says(tmp_path, variant, log):
    """P.7: the store said ``{x : (x - c)^T A (x - c) <= 1}`` while it stores the scaled
    covariance (the inverse convention), and in the default variant centre and matrix are in
    each model's unit prior box with nothing saying so. Read the descriptions, map the
    particles as they say, and the survivors of each population lie in its ellipsoids (the
    paper variant's one ellipsoid holds every survivor by construction; the evidence
    variant's union holds every point but far outliers: at least 95 %). With log-uniform
    priors the descriptions name the parameters whose log theta the frame holds."""
    store = line_and_disc_store(tmp_path / "g.zarr", variant, log=log)
    ds = xr.open_zarr(store.path)
    convention = "{x : (x - c)^T M^-1 (x - c) <= 1}"
    assert convention in ds["ellipsoid_matrix"].attrs["description"]
    assert convention in ds["ellipsoid_centre"].attrs["description"]
    frame = ds.attrs["ellipsoid_frame"]
    assert frame == {"evidence": "unit prior box", "paper": "parameters"}[variant]
    unit = "x = (theta - prior_low) / prior_width"
    assert (unit in ds["ellipsoid_matrix"].attrs["description"]) == (frame == "unit prior box")
    named = "for line.a, disc.a, disc.b (log-uniform priors) log theta in place of theta"
    assert (named in ds["ellipsoid_matrix"].attrs["description"]) == log
    assert ds["prior_low"].sel(model="disc").values.tolist() == [2.0, 0.5 if log else -30.0]
    assert float(ds["prior_width"].sel(model="line", parameter="a")) == 5.0
    for name in ("line", "disc"):
        view = model_view(ds, name)
        for t in ds["population"].values[:-1]:
            row = view.sel(population=t)
            theta = row["theta"].values[row["survivor"].values]
            low, width = row["prior_low"].values, row["prior_width"].values
            if log:
                theta, low, width = np.log(theta), np.log(low), np.log1p(width / low)
            x = (theta - low) / width if frame == "unit prior box" else theta
            inside = np.zeros(x.shape[0], bool)
            for e in range(ds.sizes["ellipsoid"]):
                c, m = row["ellipsoid_centre"].values[e], row["ellipsoid_matrix"].values[e]
                if np.isnan(c).any():
                    continue
                diff = x - c
                inside |= np.einsum("ij,ij->i", diff, np.linalg.solve(m, diff.T).T) <= 1 + 1e-9
            share = inside.mean()
            assert share == 1.0 if variant == "paper" else share >= 0.95, (name, t, share)


def test_plain_xarray_opens_the_store_and_one_model_is_one_call(tmp_path):
    """Q.13: plain ``xr.open_zarr(path)`` warned about consolidated metadata (an error here:
    filterwarnings = error), between appends too; one model's particles needed
    ``where(model_index == 1)``. The store keeps consolidated metadata as of its last complete
    population, ``model_view`` / ``Store.model`` give one model's part, and theta says what
    its units are. The per-model failure counters are stored (P.1)."""
    store = line_and_disc_store(tmp_path / "v.zarr", "evidence", n_populations=3)
    ds = xr.open_zarr(store.path)
    assert ds.sizes["population"] == 3 and store.dataset().identical(ds)
    disc = store.model("disc")
    assert disc["parameter"].values.tolist() == ["a", "b"] and disc.attrs["model"] == "disc"
    mine = ds["model_index"].values == 1
    assert same_bits(disc["theta"].values[mine], ds["theta"].values[mine])
    assert np.isnan(disc["theta"].values[~mine]).all() and not disc["survivor"].values[~mine].any()
    assert same_bits(disc["model_probability"].values, ds["model_probability"].sel(model="disc").values)
    line = model_view(ds, "line")
    assert line["parameter"].values.tolist() == ["a"] and line["ellipsoid_matrix"].shape[-2:] == (1, 1)
    with pytest.raises(KeyError, match="no model 'cubic'"):
        model_view(ds, "cubic")
    assert "those of the simulator's equations" in ds["theta"].attrs["description"]
    pops = store.populations()
    assert ds["n_failed_by_model"].values.tolist() == [p.n_failed_by_model.tolist() for p in pops] == [[0, 0]] * 3
    assert (ds["n_simulations_by_model"].values.sum(axis=1) == ds["n_simulations"].values).all()
    # between appends a plain reader sees whole populations only, without a warning
    pop = pops[-1]
    store.append(replace(pop, t=4), n_simulations_total=0)
    assert xr.open_zarr(store.path).sizes["population"] == 4


def test_writing_a_store_needs_no_warning_scope_and_consolidates_as_zarr_does(tmp_path, monkeypatch):
    """The store's consolidated metadata was written by ``zarr.consolidate_metadata``, which
    warns that zarr 3 has not standardised it; a scope of ``catch_warnings`` hid the warning.
    Such a scope is process-wide (before Python 3.14): another thread's scope that ends
    meanwhile (numba's, loading a kernel in the runner's thread) restores the filters it saw
    and drops the store's, and the warning escaped (an error under ``filterwarnings =
    error``). Creating, appending and setting a status now ask for no scope: with the scope
    made a no-op, nothing warns. And what the store writes is what zarr would: the
    consolidated metadata equals ``zarr.consolidate_metadata``'s for the same store."""
    def no_scope(message):
        return contextlib.nullcontext()

    monkeypatch.setattr(store_metadata, "ignoring", no_scope)
    store = line_and_disc_store(tmp_path / "w.zarr", "evidence", n_populations=2)  # create, append: warnings are errors
    store.set_status("finished", StopReason.MAX_POPULATIONS)
    ours = json.loads((store.path / "zarr.json").read_text())
    with pytest.warns(zarr.errors.ZarrUserWarning, match="Consolidated metadata is currently not part"):
        zarr.consolidate_metadata(str(store.path), zarr_format=3)
    theirs = json.loads((store.path / "zarr.json").read_text())
    assert ours == theirs and sorted(ours["consolidated_metadata"]["metadata"]) == sorted(v.name for v in SCHEMA)
    assert ours["consolidated_metadata"]["metadata"]["theta"]["shape"][0] == 2


# ---------------------------------------------------------------- S: the schema declared once, the format unchanged
FORMAT_SNAPSHOT = Path(__file__).parent / "data" / "store_format_4.json"


def fixed_population(t: int) -> Population:
    """A population of fixed numbers (no random stream, no linear algebra: the same bytes on
    any machine) with every part a store holds: particles of two models of 1 and 2
    parameters, survivors, ellipsoids (one dead model at t = 3), evidence, the noise floor and
    the per-model counters; t = 2 has none of the optional parts (their fills are stored)."""
    n, full = 4, t != 2
    theta = np.array([[0.1 * t, np.nan], [0.2, 0.3], [0.4, 0.5 * t], [0.6, 0.7]])
    bounds = ((ell.from_matrix(np.array([0.5]), np.array([[0.04 * t]]), "repaired"),) if t != 3 else (),
              (ell.from_matrix(np.array([0.5, 0.25]), np.diag([0.01, 0.02 * t])),
               ell.from_matrix(np.array([0.1, 0.9]), np.diag([0.03, 0.01]), "box")))
    evidence = Evidence(**{name: np.array([-0.5 * t, -1.25]) for name in Evidence.FLOATS},
                        **{name: np.array([t, 7], dtype=np.int64) for name in Evidence.INTS})
    return Population(
        t=t, epsilon=2.0 / t, epsilon_next=1.0 / t, models=np.array([0, 1, 1, 1], dtype=np.int16), theta=theta,
        distances=np.array([0.5, 0.25, 0.125, 1.0]) / t, weights=np.array([1.0, 0.5, 0.25, 0.25]),
        n_accepted=n, n_simulations=10 * t, n_failed=t, n_redraws=3, elapsed_s=0.5 * t,
        survivors=np.array([True, False, True, t == 1]) if full else None, ellipsoids=bounds if full else (),
        model_probabilities=np.array([0.25, 0.75]), evidence=evidence if full else None,
        n_simulations_by_model=np.array([4 * t, 6 * t]) if full else np.zeros(0, dtype=np.int64),
        n_failed_by_model=np.array([0, t]) if full else np.zeros(0, dtype=np.int64),
        floor=Floor(0.0625, 1, 2, 0.001, 0, 500) if full else None,
        held=np.array([[1, -1], [-1, -1], [-1, 1], [1, 0]], dtype=np.int8) if full else None,
    )


def format_snapshot(path: Path) -> dict:
    """Everything a store's format is: each array's zarr metadata (shape, chunks, dtype, fill,
    codecs, dimension names, attributes) and its decoded content, and the group attributes
    but the times and versions."""
    group = zarr.open_group(str(path), mode="r")
    arrays = {}
    for name in sorted(group.array_keys()):
        meta = json.loads((path / name / "zarr.json").read_text())
        data = np.asarray(group[name][...])
        raw = "\x1f".join(data.ravel().tolist()).encode() if data.dtype.kind in "OUT" else data.tobytes()
        meta["content"] = f"{data.dtype.str}{data.shape} sha256:{hashlib.sha256(raw).hexdigest()}"
        arrays[name] = meta
    attrs = {k: v for k, v in group.attrs.asdict().items() if k not in ("created_at", "updated_at", "versions")}
    return {"attributes": attrs, "arrays": arrays}


def write_format_store(path: Path) -> Store:
    models = [abcns.Model("line", {"a": (0, 1)}), abcns.Model("disc", {"a": (0, 1), "b": (-2, 2)})]
    spec = {"models": [m.config_dict() for m in models], "sampler": {"particles": 4}}
    store = Store.create(path, spec=spec, seed=5, model_names=["line", "disc"], parameter_names=[["a"], ["a", "b"]],
                         n_particles=4, data_hash=data_hash(np.arange(3.0)), algorithm="abc-ns", max_ellipsoids=2)
    store.append_many([(fixed_population(1), 10), (fixed_population(2), 30)])
    store.append(fixed_population(3), n_simulations_total=60)
    store.set_status("finished", "max_populations", run={"n_simulations": 60, "notes": ["fixed"]})
    return store


def test_the_format_is_the_one_written_before_the_schema_was_declared_once(tmp_path):
    """S: the schema moved into one declaration (SCHEMA) without changing format 4.
    tests/data/store_format_4.json was written by this test's helpers at commit 61e915e (the
    code before the change: ``python -c 'from tests.test_store import *;
    print(json.dumps(format_snapshot(write_format_store(Path("x.zarr")).path), indent=1,
    sort_keys=True))'``); a store written now holds the same arrays, metadata and content,
    and reads back as written. One text changed since: survivor's description said "kept
    from the previous population" while survivor marks the particles kept for the next one.
    Format 7 is format 4 with one array more, ``held`` (per particle and model), and two
    fewer, ``evidence_coverage`` and ``evidence_n_coverage`` (the evidence from the mixture
    of the proposal regions needs no coverage)."""
    store = write_format_store(tmp_path / "f.zarr")
    want = json.loads(FORMAT_SNAPSHOT.read_text())
    got = json.loads(json.dumps(format_snapshot(store.path)))  # JSON's view (NaN fills, tuples as lists)
    assert got["attributes"] == want["attributes"] | {"format_version": 7}
    gone = {"evidence_coverage", "evidence_n_coverage"}
    assert sorted(got["arrays"]) == sorted([*(set(want["arrays"]) - gone), "held"])
    for name in set(want["arrays"]) - gone:
        assert got["arrays"][name] == want["arrays"][name], name
    for pop, back in zip([fixed_population(t) for t in (1, 2, 3)], Store.open(store.path).populations()):
        assert_same_population(pop, back)
        assert back.floor == pop.floor


def test_a_store_and_its_dataset_give_one_result_while_the_run_goes_on(tmp_path):
    """S: the runner and the export built a Result from a store twice, with different
    fallbacks: a store whose run has not ended (no run information yet) gave 0 simulations
    and 0 s through the dataset and the store's own counters through the store. One
    builder (result_of) now: the store's last n_simulations_total and elapsed_s either way.
    Its models are the spec's, in either form a spec holds (Model.from_dict)."""
    store = Store.create(tmp_path / "r.zarr", spec={"models": [
        {"name": "line", "simulator": "toy", "priors": {"a": [0, 1]}},  # a job spec's form
        abcns.Model("disc", {"a": (0, 1), "b": (-2, 2)}, config={"simulator": "toy"}).config_dict()]},
        seed=5, model_names=["line", "disc"], parameter_names=[["a"], ["a", "b"]], n_particles=4, data_hash="",
        algorithm="abc-ns", max_ellipsoids=2)
    store.append_many([(fixed_population(1), 10), (fixed_population(2), 30)])
    direct, through = result_from_store(store), dataset_result(store.dataset())
    for r in (direct, through):
        assert (r.n_simulations, r.wall_time_s, r.stop_reason) == (30, 1.0, StopReason.CANCELLED)
        assert [m.config_dict() for m in r.models] == [
            {"name": "line", "priors": {"a": [0.0, 1.0]}, "fixed": {}, "config": {"simulator": "toy"}},
            {"name": "disc", "priors": {"a": [0.0, 1.0], "b": [-2.0, 2.0]}, "fixed": {}, "config": {"simulator": "toy"}}]
    assert repr(direct.summary()) == repr(through.summary())
    store.set_status("finished", "max_populations", run={"n_simulations": 45, "wall_time_s": 2.5})
    assert (result_from_store(store).n_simulations, dataset_result(store.dataset()).wall_time_s) == (45, 2.5)


def test_the_descriptions_are_true_of_a_real_run(reference):
    """S: the store's variables were checked for having a description, not for its being
    true. Each claim below is read from the description (so a changed text fails here) and
    checked against a real run (the reference store: 5 populations of two_models, ABC-NS)."""
    store, _pops, totals = reference
    ds = xr.open_zarr(store.path)
    a = {name: ds[name].values for name in ds.variables}
    say = {name: ds[name].attrs["description"] for name in ds.variables}
    for name in ds.variables:  # the dimensions and dtypes the schema declares
        v = next(v for v in SCHEMA if v.name == name)
        assert ds[name].dims == ((("population",) if v.grows and name != "population" else ()) + v.dims or (name,)), name
    assert "kept for the next population" in say["survivor"]
    for t in range(4):  # every survivor of t is a particle of t + 1, as it was
        nxt = {(m, x.tobytes()) for m, x in zip(a["model_index"][t + 1], a["theta"][t + 1])}
        assert all((m, x.tobytes()) in nxt for m, x in zip(a["model_index"][t][a["survivor"][t]],
                                                             a["theta"][t][a["survivor"][t]]))
    assert "sum to 1 within each model" in say["weight"]
    for t in range(5):
        for m in range(2):
            w = a["weight"][t][a["model_index"][t] == m]
            assert w.size == 0 or abs(w.sum() - 1) < 1e-12
    assert say["acceptance_rate"] == "accepted / simulated in this population"
    assert np.array_equal(a["acceptance_rate"], a["n_accepted"] / a["n_simulations"])
    assert "cumulative" in say["n_simulations_total"] and a["n_simulations_total"].tolist() == totals
    assert np.array_equal(a["n_simulations_total"], np.cumsum(a["n_simulations"]))  # no pilot: epsilon_initial given
    assert "accepted under" in say["epsilon"] and all((a["distance"][t] < a["epsilon"][t]).all() for t in range(5))
    assert "for the next population" in say["epsilon_next"]
    assert np.array_equal(a["epsilon_next"][:-1], a["epsilon"][1:])
    assert "split by model" in say["n_simulations_by_model"] and "split by model" in say["n_failed_by_model"]
    assert np.array_equal(a["n_simulations_by_model"].sum(axis=1), a["n_simulations"])
    assert np.array_equal(a["n_failed_by_model"].sum(axis=1), a["n_failed"])
    assert np.allclose(a["model_probability"].sum(axis=1), 1, rtol=0, atol=1e-12)
    assert "index along the model dimension" in say["model_index"] and set(np.unique(a["model_index"])) <= {0, 1}
    assert "whether the model infers that parameter" in say["model_has_parameter"]
    for m in range(2):  # a model's particles have values exactly in its own parameters
        rows = a["theta"][a["model_index"] == m]
        assert np.array_equal(~np.isnan(rows).any(axis=0), a["model_has_parameter"][m])
    assert "wall time from the start of the run" in say["elapsed_s"] and (np.diff(a["elapsed_s"]) > 0).all()
    units = {name: ds[name].attrs.get("units") for name in ds.variables}
    assert {name for name, u in units.items() if u == "%"} == {  # the spec's NMSE: the distance's units
        "distance", "epsilon", "epsilon_next", "floor_best", "floor_noise_variance", "noise_floor", "decision_tolerance"}
    assert units["elapsed_s"] == "s" and all(units[n] == "1" for n in ("n_accepted", "weight", "model_probability"))


def test_a_resumed_run_says_where_its_first_tolerance_came_from(tmp_path, monkeypatch):
    """An ABC-SMC job with a tolerance schedule whose runner dies after its first population
    (here an exception in the runner's thread when population 2 is done: the run ends
    ``failed`` with population 1 stored, as a killed process leaves it, without the end
    record that says where epsilon_1 came from) and is resumed: its result and its store say
    the schedule, as the uninterrupted run's do (the runner wrote a guess, "given" or
    "pilot", with population 1, and a resumed run kept it)."""
    import service.run.runner as runner
    from service.run.runner import run_job
    from service.spec import parse

    raw = linear_demo_raw("schedule")
    raw["sampler"] = {"algorithm": "abc-smc", "particles": 50, "batch_size": 25, "schedule": [100, 60, 40, 30, 25, 20]}
    raw["stop"] = {"max_populations": 6}
    spec = parse(raw)
    whole = run_job(spec, Path("/"), tmp_path / "whole.zarr", None)
    assert whole.epsilon_initial_source == "schedule" and len(whole.populations) == 6

    def dies(pop, *args):  # runner.Progress, called in the runner's thread as each population is done
        if pop.t == 2:
            raise RuntimeError("the runner dies")
        return progress(pop, *args)

    progress = runner.Progress
    path = tmp_path / "resumed.zarr"
    with monkeypatch.context() as patch:
        patch.setattr(runner, "Progress", dies)
        with pytest.raises(RuntimeError, match="the runner dies"):
            run_job(spec, Path("/"), path, None)
    assert Store.open(path).attrs["status"] == "failed" and Store.open(path).n_populations == 1
    resumed = run_job(spec, Path("/"), path, None)
    assert len(resumed.populations) == 6
    assert resumed.epsilon_initial_source == "schedule"
    assert Store.open(path).attrs["run"]["epsilon_initial_source"] == "schedule"
