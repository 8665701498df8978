"""The registry of simulators, by name.

Built-ins: ``duffing``, ``bouc_wen``, ``linear`` (exact, for a held or a linear input), ``gandk``
(driven by a force, or none), and ``bouc_wen_restoring``, ``bwbn_restoring``, ``spencer_mr`` (driven by a measured
displacement, predicting the force: :mod:`worker.restoring`), ``spencer_mr_voltage`` (the
displacement and the coil voltage, ``data.voltage``).
Plugins: any installed package can add simulators through the entry-point group
``abcns.simulators`` (``name = "package.module:factory"``); they must be installed on the
service and on every worker. The CLI (never HTTP) may also name a local
``package.module:factory`` directly in a spec.

A simulator factory (a class or any callable) returns a
:class:`worker.simulators.Simulator`: an object with ``name``, ``parameter_names``,
``defaults`` (a dict), ``n_samples``, ``simulate(params (n, p), rng) -> SimOutput`` (values
(n, n_samples) and status (n,) with ``abcns.OK / DIVERGED / FAILED``) and ``config() ->
dict``; optionally :class:`worker.simulators.NMSECapable` (``distance_nmse(params, observed,
start, stop, epsilon)``, a fused fast path). The factory may have a static
``omega_max(bounds)`` (lets the substeps be chosen from the priors), a static
``omega_min(bounds)`` (the least that highest frequency gets over the bounds: the HTTP
service checks the sampling rate against both, ``service.spec.check_meaningful``) and ``needs_input``:
False: called as ``factory(n_samples=...)`` (the observed record's length); True: the input
is required, and the factory is called with those of the keywords ``force``, ``dt``,
``n_samples``, ``substeps``, ``output``, ``state_bound`` and ``input_interpolation`` its
signature names (all with ``**kwargs``), and ``voltage`` (``data.voltage``) when it names
that one explicitly; absent: as True, but ``force`` may be None (no
input given). See ``worker/simulators.py`` for four examples and
:func:`worker.description.simulator_for`.
"""

from __future__ import annotations

import importlib
from importlib.metadata import EntryPoint, entry_points

from abcns.errors import InvalidSetting
from worker.restoring import BoucWenRestoring, BWBNRestoring, SpencerMR, SpencerMRVoltage
from worker.simulators import BoucWen, Duffing, GAndK, Linear

BUILTINS: dict[str, type] = {cls.name: cls for cls in (Duffing, BoucWen, Linear, GAndK, BoucWenRestoring, BWBNRestoring,
                                                        SpencerMR, SpencerMRVoltage)}
GROUP = "abcns.simulators"


def plugins() -> dict[str, EntryPoint]:
    """Entry points of the group ``abcns.simulators`` (not loaded)."""
    return {ep.name: ep for ep in entry_points(group=GROUP)}


def names() -> list[str]:
    return sorted({*BUILTINS, *plugins()})


def get(name: str, allow_import: bool = False):
    """The factory registered as ``name``; with ``allow_import`` also ``package.module:factory``
    (an InvalidSetting at ``("simulator",)`` otherwise)."""
    field = ("simulator",)
    if name in BUILTINS:
        return BUILTINS[name]
    eps = plugins()
    if name in eps:
        try:
            return eps[name].load()
        except (ImportError, AttributeError) as err:
            raise InvalidSetting(field, f"plugin simulator {name!r} cannot be loaded: {err}") from None
    if ":" in name:
        if not allow_import:
            raise InvalidSetting(field, f"{name!r} names code; only registered simulators are allowed here: {names()}")
        module, _, attr = name.partition(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as err:
            raise InvalidSetting(field, f"cannot load {name!r}: {err}") from None
    raise InvalidSetting(field, f"unknown simulator {name!r}; registered: {names()}")
