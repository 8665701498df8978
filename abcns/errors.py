"""Invalid input, with where it is.

The algorithm (``abcns``) and the worker's builders (``worker``) raise :class:`InvalidSetting`
with a ``path`` in their own terms: the argument or field a caller gave, e.g. ``("settings",
"particles")``, ``("models", 1, "priors", "k")``, ``("observed",)`` (the record a distance
reads), ``("models", 0, "substeps")`` (worker.description.ModelDescription). The job spec's
layer (``service.spec``) maps those paths to the spec's own fields in one place and raises
:class:`SpecError`, whose path is the spec's (``data.observed``, ``models[0].integrator.substeps``).
"""

from __future__ import annotations

from collections.abc import Sequence

Path = tuple[str | int, ...]


def dotted(path: Sequence[str | int]) -> str:
    """A path as text: names joined by dots, list positions in brackets (``models[1].priors.k``)."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


class InvalidSetting(ValueError):
    """Invalid input at ``path`` (a tuple of names and list positions), with ``message``."""

    def __init__(self, path: Path, message: str):
        self.path: Path = tuple(path)
        self.message = message
        super().__init__(f"{self.field}: {message}")

    @property
    def field(self) -> str:
        """The path as text (:func:`dotted`)."""
        return dotted(self.path)

    def within(self, *prefix: str | int) -> InvalidSetting:
        """The same error one level up: its path behind ``prefix`` (``("models", 0)``)."""
        return type(self)((*prefix, *self.path), self.message)

    def __reduce__(self):  # pickled (a Dask task's error) with its path, not its text only
        return type(self), (self.path, self.message)


class SpecError(InvalidSetting):
    """Invalid input in a job spec's terms: ``field`` names the spec's field, e.g.
    ``models[1].priors.k`` (``service.spec`` raises it, and maps the core's errors to it)."""

    def __init__(self, field: str | Path, message: str):
        super().__init__((field,) if isinstance(field, str) else field, message)
