"""The registry of simulators, by name.

Built-ins: ``duffing``, ``bouc_wen``, ``linear`` (exact zero-order hold), ``gandk``.
Plugins: any installed package can add simulators through the entry-point group
``abcns.simulators`` (``name = "package.module:factory"``); they must be installed on the
service and on every worker. The CLI (never HTTP) may also name a local
``package.module:factory`` directly in a spec.

A simulator factory is called with keyword arguments ``force`` (the input, or None),
``dt``, ``n_samples`` (the observed record's length), ``substeps``, ``output`` and
``state_bound``, and returns an object with ``parameter_names``, ``defaults`` (a dict),
``n_samples``, ``simulate(params (n, p), rng) -> SimOutput`` (values (n, n_samples) and
status (n,) with ``abcns.OK / DIVERGED / FAILED``) and ``config() -> dict``; optionally
``distance_nmse(params, observed, start, stop, epsilon)`` (a fused fast path) and a static
``omega_max(bounds)`` (lets the substeps be chosen from the priors). See
``worker/simulators.py`` for four examples.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points

from abcns.priors import SpecError
from worker.simulators import BoucWen, Duffing, GAndK, Linear

BUILTINS: dict[str, type] = {cls.name: cls for cls in (Duffing, BoucWen, Linear, GAndK)}
GROUP = "abcns.simulators"


def plugins() -> dict[str, object]:
    """Entry points of the group ``abcns.simulators`` (not loaded)."""
    return {ep.name: ep for ep in entry_points(group=GROUP)}


def names() -> list[str]:
    return sorted({*BUILTINS, *plugins()})


def get(name: str, field: str = "simulator", allow_import: bool = False):
    """The factory registered as ``name``; with ``allow_import`` also ``package.module:factory``."""
    if name in BUILTINS:
        return BUILTINS[name]
    eps = plugins()
    if name in eps:
        try:
            return eps[name].load()  # type: ignore[attr-defined]
        except (ImportError, AttributeError) as err:
            raise SpecError(field, f"plugin simulator {name!r} cannot be loaded: {err}") from None
    if ":" in name:
        if not allow_import:
            raise SpecError(field, f"{name!r} names code; only registered simulators are allowed here: {names()}")
        module, _, attr = name.partition(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as err:
            raise SpecError(field, f"cannot load {name!r}: {err}") from None
    raise SpecError(field, f"unknown simulator {name!r}; registered: {names()}")
