"""A user's simulator with a bug (for tests/test_cli.py): the Duffing oscillator, raising a
RuntimeError for any batch holding a damping above 0.19 (the authors' prior is [0.002, 0.2],
so population 1 has such rows)."""

from worker.simulators import Duffing


class Faulty(Duffing):
    def _check(self, params):
        if (params[:, 1] > 0.19).any():
            raise RuntimeError("a bug in the user's simulator")

    def simulate(self, params, rng):
        self._check(params)
        return super().simulate(params, rng)

    def distance_nmse(self, params, *args, **kwargs):
        self._check(params)
        return super().distance_nmse(params, *args, **kwargs)
