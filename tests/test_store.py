"""The zarr result store: exact round trip, resume from a store, crash-safe appends,
xarray while a job runs, attributes and errors."""

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
from abcns import NSSettings, Population, SerialExecutor, StopReason, StopRules
from abcns import ellipsoid as ell
from abcns.filling import Budget
from service.store import FORMAT_VERSION, NOTE_CODES, PARTIAL_WARNING, Store, StoreError, StoreNotFound, data_hash
from tests.closed_form import two_models

SETTINGS = NSSettings(particles=200, epsilon_initial=2.0, batch_size=50)
SEED = 3
SPEC = {"name": "two-models", "sampler": {"particles": 200, "epsilon_initial": 2.0, "batch_size": 50}, "seed": SEED}
ARRAYS = ("models", "theta", "distances", "weights", "survivors", "model_probabilities")
SCALARS = ("t", "epsilon", "epsilon_next", "n_accepted", "n_simulations", "n_failed", "n_redraws")


def stop_after(n: int) -> StopRules:
    return StopRules(min_epsilon_decrease=None, max_populations=n)


def new_store(path: Path, models, n_particles: int = 200, **kw) -> Store:
    args = dict(spec=SPEC, seed=SEED, model_names=[m.name for m in models],
                parameter_names=[list(m.parameter_names) for m in models], n_particles=n_particles,
                data_hash=data_hash(np.array([0.5])), algorithm="abc-ns")
    return Store.create(path, **{**args, **kw})


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
    for i, (e, f) in enumerate(zip(a.ellipsoids, b.ellipsoids)):
        assert (e is None) == (f is None), f"population {a.t}: ellipsoid {i}"
        if e is not None:
            for name in ("centre", "matrix", "axes"):
                assert same_bits(getattr(e, name), getattr(f, name)), f"population {a.t}: ellipsoid {i} {name}"
            assert e.log_volume == f.log_volume and e.note == f.note


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
        with pytest.raises(IndexError, match="holds populations 1..5"):
            store.population(t)
    g = zarr.open_group(str(store.path), mode="r")
    assert g["n_simulations_total"][:].tolist() == totals
    assert store.run_state() == {"n_populations": 5, "t": 5, "n_simulations_total": totals[-1],
                                 "elapsed_s": pops[-1].elapsed_s}


def test_resume_from_store_equals_uninterrupted_run(reference, tmp_path):
    store_a, pops_a, totals_a = reference
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
            assert done.value.reason is StopReason.MAX_POPULATIONS
            break
        store_b.append(pop, n_simulations_total=budget.n_simulations)

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
        assert dict(ds.sizes) == {"population": pop.t, "particle": 200, "model": 2, "parameter": 1, "parameter_b": 1}
        assert ds["population"].values.tolist() == list(range(1, pop.t + 1))
        assert ds["model_name"].values.tolist() == ["narrow", "wide"]
        assert ds["model"].dims == ("population", "particle") and ds["model"].dtype == np.int16
        assert ds["ellipsoid_matrix"].dims == ("population", "model", "parameter", "parameter_b")
        assert ds["model_probability"].dims == ("population", "model")
        assert ds["epsilon"].dims == ("population",)
        assert store.dataset().identical(ds)
        row = ds.sel(population=pop.t)
        assert same_bits(row["model"].values, pop.models)
        assert same_bits(row["theta"].values, pop.theta)
        assert same_bits(row["distance"].values, pop.distances)
        assert same_bits(row["weight"].values, pop.weights)
        assert same_bits(row["survivor"].values, pop.survivors)
        assert same_bits(row["model_probability"].values, pop.model_probabilities)
        assert float(row["epsilon"]) == pop.epsilon and float(row["epsilon_next"]) == pop.epsilon_next
        assert float(row["acceptance_rate"]) == pop.acceptance_rate
        assert int(row["n_simulations"]) == pop.n_simulations and int(row["n_failed"]) == pop.n_failed
        assert int(row["n_simulations_total"]) == total
        for i, e in enumerate(pop.ellipsoids):
            assert same_bits(row["ellipsoid_centre"].values[i], e.centre)
            assert same_bits(row["ellipsoid_matrix"].values[i], e.matrix)
            assert int(row["ellipsoid_note"].values[i]) == NOTE_CODES[e.note]


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
        ellipsoids=() if baseline else (None, e),
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
    assert {b.ellipsoids[1].note for b in back[1:]} == {"", "repaired", "fallback", "box"}
    ds = xr.open_zarr(store.path, consolidated=False)
    assert ds["parameter_name"].values.tolist() == [["a", "", ""], ["x", "y", "z"]]
    assert np.isnan(ds["ellipsoid_matrix"].values[:, 0]).all()  # the dead model
    assert ds["ellipsoid_note"].values[:, 0].tolist() == [-1] * 5


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
    assert attrs["format_version"] == FORMAT_VERSION == 1
    assert attrs["spec"] == SPEC and attrs["seed"] == SEED and attrs["algorithm"] == "abc-ns"
    assert attrs["data_hash"] == data_hash(np.array([0.5]))
    assert attrs["model_names"] == ["narrow", "wide"] and attrs["parameter_names"] == [["theta"], ["theta"]]
    assert set(attrs["versions"]) == {"abcns", "numpy", "scipy", "zarr", "python"}
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


def test_open_and_create_errors(tmp_path):
    with pytest.raises(StoreNotFound, match="does not exist"):
        Store.open(tmp_path / "missing.zarr")
    (tmp_path / "empty").mkdir()
    with pytest.raises(StoreError, match="not a result store"):
        Store.open(tmp_path / "empty")
    zarr.open_group(str(tmp_path / "plain.zarr"), mode="w", zarr_format=3).attrs["x"] = 1
    with pytest.raises(StoreError, match="not a result store .no format_version"):
        Store.open(tmp_path / "plain.zarr")

    models, _ = two_models()
    store = new_store(tmp_path / "empty", models)  # an empty directory is fine
    zarr.open_group(str(store.path), mode="r+").attrs["format_version"] = 2
    with pytest.raises(StoreError, match="format_version 2; this abcns reads version 1"):
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
    assert data_hash(x) != data_hash(x + 1e-12)
    assert data_hash(x[::2]) == data_hash(np.ascontiguousarray(x[::2]))
    with pytest.raises(TypeError):
        data_hash(np.array([None]))


def test_status_set_by_another_process_during_an_append_is_kept(reference, tmp_path, monkeypatch):
    _, pops, totals = reference
    models, _ = two_models()
    writer = new_store(tmp_path / "s.zarr", models)
    commit = Store._commit

    def late(self, n):  # the scheduler cancels between the data and the counter
        Store.open(self.path).set_status("cancelled", stop_reason="cancelled")
        commit(self, n)

    monkeypatch.setattr(Store, "_commit", late)
    writer.append(pops[0], n_simulations_total=totals[0])
    attrs = Store.open(writer.path).attrs
    assert attrs["status"] == "cancelled" and attrs["n_populations"] == 1
    assert xr.open_zarr(writer.path, consolidated=False).sizes["population"] == 1


@pytest.mark.filterwarnings(f"ignore:{PARTIAL_WARNING}:zarr.errors.ZarrUserWarning")
def test_a_reader_polling_during_appends_sees_only_complete_populations(reference, tmp_path):
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
                assert not np.isnan(ds["distance"].values).any() and (ds["model"].values >= 0).all()
                assert (ds["n_simulations_total"].values == totals[:n]).all()
                seen.append(n)
            except Exception as err:  # reported below
                errors.append(err)
                return

    thread = threading.Thread(target=poll)
    thread.start()
    try:
        for pop, total in zip(pops, totals):
            store.append(pop, n_simulations_total=total)
            time.sleep(0.05)
    finally:
        done.set()
        thread.join()
    assert not errors, errors
    assert seen and seen == sorted(seen) and seen[-1] <= 5
