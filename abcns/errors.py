"""Invalid input, with where it is: :class:`InvalidSetting`, raised by ``abcns`` and ``worker``
at a path in their own terms (the argument or field they were given: ``("settings",
"particles")``, ``("models", 1, "priors", "k")``, ``("force",)``), and :class:`SpecError`, in the
job spec's terms, which ``service.spec`` maps the core's paths to in one place (docs/design.md).
"""

from __future__ import annotations

from collections.abc import Sequence


def dotted(path: Sequence[str | int]) -> str:
    """A path as text: names joined by dots, list positions in brackets (``models[1].priors.k``)."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


class InvalidSetting(ValueError):
    """Invalid input at ``path`` (a tuple of names and list positions), with ``message``."""

    def __init__(self, path: tuple[str | int, ...], message: str):
        self.path, self.message = tuple(path), message
        super().__init__(f"{self.field}: {message}")

    @property
    def field(self) -> str:
        return dotted(self.path)

    def within(self, *prefix: str | int) -> InvalidSetting:
        """The same error one level up: its path behind ``prefix`` (``("models", 0)``)."""
        return type(self)((*prefix, *self.path), self.message)

    def __reduce__(self):  # pickled (a Dask task's error) with its path, not its text only
        return type(self), (self.path, self.message)


class SpecError(InvalidSetting):
    """Invalid input in a job spec: ``field`` names the spec's field (``models[1].priors.k``)."""

    def __init__(self, field: str | tuple[str | int, ...], message: str):
        super().__init__((field,) if isinstance(field, str) else field, message)
