"""The registry of simulators, by name.

Built-ins: ``duffing``, ``bouc_wen``, ``linear`` (exact zero-order hold), ``gandk``.
Later: plugins through the entry-point group ``abcns.simulators``.
"""

from __future__ import annotations

from abcns.priors import SpecError
from worker.simulators import BoucWen, Duffing, GAndK, Linear

SIMULATORS: dict[str, type] = {cls.name: cls for cls in (Duffing, BoucWen, Linear, GAndK)}


def get(name: str, field: str = "simulator") -> type:
    try:
        return SIMULATORS[name]
    except KeyError:
        raise SpecError(field, f"unknown simulator {name!r}; registered: {sorted(SIMULATORS)}") from None
