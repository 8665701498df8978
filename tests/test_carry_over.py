"""Carry-over (``sampler.carry_over``, issue 24): population t + 1 first uses the next batches
of population t's stream, each row a proposal of t + 1 only when it lies in t + 1's region,
which is nested in t's. What must hold: the regions are nested (so those rows are uniform
there), the rows outside are counted but not proposed, and the result is a property of the
job: the same on any executor, on any number of Dask workers, resumed or not."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from distributed import Client

from abcns import NSSettings, SerialExecutor, StopRules, run
from abcns import bounds as bd
from abcns import ellipsoid as ell
from abcns.nested import abc_ns
from abcns.priors import SpecError
from service.run.dask_executor import local_cluster
from service.run.runner import run_job
from service.run.store import Store
from service.spec import parse
from tests.closed_form import line_and_disc, two_models
from tests.test_store import assert_same_population

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "data" / "authors-demo" / "demo_data.npz"


def test_the_paper_variant_refuses_carry_over():
    with pytest.raises(SpecError, match=r"sampler\.carry_over"):
        NSSettings(variant="paper", carry_over=2)
    with pytest.raises(SpecError, match=r"sampler\.carry_over"):
        NSSettings(carry_over=-1)
    assert NSSettings(variant="paper").n_carry == 0 and NSSettings(carry_over=0).n_carry == 0


def _settings(carry_over: int | None) -> NSSettings:
    return NSSettings(particles=300, epsilon_initial=0.3, batch_size=40, carry_over=carry_over)


@pytest.fixture(scope="module")
def line_disc_runs():
    """line_and_disc (a line and a disc in the unit square), seed 5, 8 populations, with 6
    batches carried over and without."""
    models, evaluate = line_and_disc()
    stop = StopRules(min_epsilon_decrease=None, max_populations=8)
    return {c: run(models, evaluate, _settings(c), stop, seed=5) for c in (6, 0)}


def test_proposals_lie_in_every_earlier_bound(line_disc_runs):
    """The proposers of populations 4 to 8 (as a run resumed there makes them) draw only
    points that lie in every earlier bound of their model; the same bounds without their
    chains draw points outside them (the enlarged fits reach past the earlier bounds), which
    is why rows carried from the previous region could not be uniform on the next one
    without nesting."""
    from abcns.filling import Budget
    from abcns.nested import _Run

    r = line_disc_runs[6]
    assert not any("not nested" in n for n in r.notes)
    models, evaluate = line_and_disc()
    stop = StopRules()
    rng = np.random.default_rng(0)
    frame = bd.Frame(models[1], unit=True)

    def outside(p, history) -> int:
        which, theta, _ = p(4000, rng)
        x = frame.to_frame(theta[which == 1, :2])
        assert x.shape[0] > 200
        return sum(int(np.count_nonzero(bd.n_inside(pop.ellipsoids[1], x) == 0)) for pop in history[:-1])

    unnested = 0
    for k in range(3, 8):
        history = r.populations[:k]
        state = _Run(models, SerialExecutor(evaluate), _settings(6), stop, 5, Budget(stop), history, None)
        state.within = state._settled(history[-1])
        proposer = state.proposer(history[-1].ellipsoids, history[-1].evidence.allocation)
        assert outside(proposer, history) == 0
        unnested += outside(replace(proposer, within=()), history)
    assert unnested > 0


def test_carried_rows_outside_the_region_are_simulations_not_proposals(line_disc_runs):
    with_carry, without = line_disc_runs[6], line_disc_runs[0]
    for r, carries in ((with_carry, True), (without, False)):
        dropped = [p.n_simulations - int(p.evidence.n_proposed.sum()) for p in r.populations]
        assert dropped[0] == 0  # the first population carries nothing
        assert min(dropped) >= 0
        assert (sum(dropped) > 0) == carries
        for p in r.populations:
            assert p.n_simulations_by_model.sum() == p.n_simulations


def test_resumed_after_any_population_the_run_is_the_same():
    """two_models (particles 200, batches of 50, 6 carried): resumed from each population's
    history, every later population equals the uninterrupted run's; among them populations
    that filled within the carried batches (the resumed stream must start after those)."""
    models, evaluate = two_models()
    settings = NSSettings(particles=200, epsilon_initial=2.0, batch_size=50, carry_over=6)
    stop = StopRules(min_epsilon_decrease=None, max_populations=7)
    whole = run(models, evaluate, settings, stop, seed=3).populations
    assert any(p.t > 1 and p.n_simulations <= 6 * 50 for p in whole)  # filled within the carried batches
    assert any(p.n_simulations > 6 * 50 for p in whole[1:])
    for k in range(1, len(whole)):
        gen = abc_ns(models, SerialExecutor(evaluate), settings, stop, 3, history=whole[:k])
        for a, b in zip(whole[k:], gen, strict=True):
            assert_same_population(a, b, elapsed=False)


def _evidence_spec(tmp_path: Path, **stop) -> Path:
    raw = yaml.safe_load((ROOT / "examples" / "authors_demo" / "evidence.yaml").read_text())
    raw["data"]["input"] = f"{DEMO}:force"
    raw["data"]["observed"] = f"{DEMO}:displacement"
    raw["sampler"] = {"particles": 300, "batch_size": 20, "carry_over": 6}
    raw["stop"] = {"min_epsilon_decrease": None, "max_populations": 5, **stop}
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.distributed
def test_dask_workers_give_the_in_process_result_also_when_cancelled_and_resumed(tmp_path):
    """The authors' demo data, evidence variant, 6 batches carried: in this process, on 3
    Dask worker processes, and on 3 workers cancelled at three quarters of the in-process
    run's budget checks between batches, the run's own order) and resumed: the same
    populations, bit for bit."""
    spec_path = _evidence_spec(tmp_path)
    spec = parse(yaml.safe_load(spec_path.read_text()))
    checks = [0]

    def between_batches() -> bool:
        """Asked by Budget.check (between batches), not by the executor while it waits."""
        return sys._getframe(3).f_code.co_name == "check"  # this <- cancel <- Budget.reason <- Budget.check

    def count() -> bool:
        checks[0] += between_batches()
        return False

    reference = run_job(spec, spec_path.parent, tmp_path / "serial.zarr", None, cancel=count)
    three_quarters, asked = checks[0] * 3 // 4, [0]  # population 1 (and the pilot) hold half of them

    def halfway() -> bool:
        asked[0] += between_batches()
        return asked[0] >= three_quarters

    with local_cluster(3) as cluster, Client(cluster) as client:
        run_job(spec, spec_path.parent, tmp_path / "dask.zarr", client)
        run_job(spec, spec_path.parent, tmp_path / "resumed.zarr", client, cancel=halfway)
        cancelled = Store.open(tmp_path / "resumed.zarr")
        assert cancelled.attrs["status"] == "cancelled" and 1 <= cancelled.n_populations < 5
        run_job(spec, spec_path.parent, tmp_path / "resumed.zarr", client)
    assert len(reference.populations) == 5
    for name in ("dask.zarr", "resumed.zarr"):
        pops = Store.open(tmp_path / name).populations()
        assert len(pops) == 5
        for a, b in zip(reference.populations, pops, strict=True):
            assert_same_population(a, b, elapsed=False)


def test_an_ellipsoid_inside_another_is_found_and_drops_from_the_chain():
    big = ell.from_matrix(np.zeros(2), np.eye(2))
    small = ell.from_matrix(np.array([0.3, 0.0]), 0.25 * np.eye(2))  # radius 0.5 at 0.3: inside
    poking = ell.from_matrix(np.array([0.6, 0.0]), 0.25 * np.eye(2))  # reaches 1.1: not inside
    assert bd.holds_ellipsoid(big, small) and not bd.holds_ellipsoid(big, poking)
    assert not bd.holds_ellipsoid(small, big)
    assert bd.nest(((big,),), (small,)) == ((small,),)  # the big one cuts nothing more
    assert bd.nest(((big,),), (poking,)) == ((big,), (poking,))
    assert bd.nest(None, (small,)) == ((small,),) and bd.nest(((big,),), ()) == ((big,),)


def test_a_region_mostly_outside_its_chain_is_not_nested():
    rng = np.random.default_rng(0)
    box = (np.zeros(2), np.ones(2))
    chain = ((ell.from_matrix(np.array([0.5, 0.5]), 0.04 * np.eye(2)),),)  # radius 0.2 at the centre
    inside = (ell.from_matrix(np.array([0.5, 0.5]), 0.01 * np.eye(2)),)
    away = (ell.from_matrix(np.array([0.78, 0.78]), 0.04 * np.eye(2)),)  # overlaps the chain's by < 1 %
    assert bd.settle(chain, inside, box, rng) == chain
    assert bd.settle(chain, away, box, rng) is None
    assert bd.settle((), away, box, rng) == () and bd.settle(chain, (), box, rng) == ()
