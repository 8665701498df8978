"""xarray / ArviZ export round trips (a small closed-form run, seed 5; no simulator)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr
from zarr.errors import UnstableSpecificationWarning

from abcns import OK, Model, NSSettings, StopRules, per_model, run
from service.report.export import from_dataset, to_dataset, to_inference_data


def small_run(seed: int = 5):
    """Two models of different dimension (1 and 2 parameters), distance |theta_0 - 0.5|
    (+ |theta_1| for the second), so the run pads theta and both models live."""
    models = [Model("one", {"a": (-2.0, 2.0)}), Model("two", {"a": (-2.0, 2.0), "b": (-1.0, 1.0)})]

    def f1(theta, rng):
        return np.abs(theta[:, 0] - 0.5) + 0.01 * rng.random(theta.shape[0]), np.full(theta.shape[0], OK, np.int8)

    def f2(theta, rng):
        d = np.abs(theta[:, 0] - 0.5) + np.abs(theta[:, 1]) + 0.01 * rng.random(theta.shape[0])
        return d, np.full(theta.shape[0], OK, np.int8)

    return run(models, per_model([f1, f2]), NSSettings(particles=200, epsilon_initial=3.0, batch_size=100),
               StopRules(max_populations=4), seed=seed)


@pytest.fixture(scope="module")
def result():
    return small_run()


def test_dataset_round_trip(result, tmp_path):
    ds = to_dataset(result)
    assert ds.sizes["population"] == 4 and ds.sizes["parameter"] == 2 and list(ds["model"].values) == ["one", "two"]
    # through a file too (zarr, a dependency already)
    with warnings.catch_warnings():  # zarr 3: the model-name strings have no stable v3 dtype spec yet
        warnings.simplefilter("ignore", UnstableSpecificationWarning)
        ds.to_zarr(tmp_path / "r.zarr", mode="w", consolidated=False)

    for back in (from_dataset(ds), from_dataset(xr.open_zarr(tmp_path / "r.zarr", consolidated=False).load())):
        assert back.model_names == result.model_names and back.stop_reason == result.stop_reason
        assert [m.config_dict() for m in back.models] == [m.config_dict() for m in result.models]
        assert back.summary()["posterior"] == result.summary()["posterior"]
        for p, q in zip(result.populations, back.populations):
            np.testing.assert_array_equal(p.models, q.models)
            np.testing.assert_array_equal(p.theta, q.theta)
            np.testing.assert_array_equal(p.distances, q.distances)
            np.testing.assert_array_equal(p.weights, q.weights)
            np.testing.assert_array_equal(p.model_probabilities, q.model_probabilities)
            assert (p.t, p.epsilon, p.epsilon_next, p.n_simulations, p.acceptance_rate) == \
                   (q.t, q.epsilon, q.epsilon_next, q.n_simulations, q.acceptance_rate)
    with pytest.raises(ValueError, match="not an abcns result"):
        from_dataset(ds.assign_attrs(format_version=1))


def test_inference_data(result):
    idata = to_inference_data(result)
    assert set(idata) == {"one", "two"}
    for i, (name, data) in enumerate(idata.items()):
        theta, dist, w = result.particles(i)
        post = data.posterior
        assert post.sizes["chain"] == 1 and post.sizes["draw"] == theta.shape[0]
        for j, p in enumerate(result.models[i].parameter_names):
            np.testing.assert_array_equal(post[p].values[0], theta[:, j])
        np.testing.assert_array_equal(data.sample_stats["distance"].values[0], dist)
        np.testing.assert_array_equal(data.sample_stats["weight"].values[0], w)
        assert data.posterior.attrs["model"] == name
