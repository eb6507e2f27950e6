"""Dataclasses whose fields, set after construction, get the checks the constructor gives.

A config made once and then changed in place (a speed preset, a command line's options, a
user's ``config.blurred = True``) would otherwise skip ``__post_init__``'s checks, and a
misspelt name would become a new attribute nobody reads.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Self


class CheckedFields:
    """Mixin for a ``@dataclass`` whose ``__post_init__`` checks its fields: a field set on a
    made instance is checked the same way, and a refused value (whatever the check raised)
    leaves the instance as it was; a name that is no field is refused."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self.__dict__:
            self.update(**{name: value})
        elif name in self.__dataclass_fields__:  # the constructor's own assignments
            object.__setattr__(self, name, value)
        else:
            raise AttributeError(f"unknown {type(self).__name__} field {name!r}")

    @classmethod
    def unknown_fields(cls, names: Iterable[str]) -> list[str]:
        """The ``names`` that are no field of the class, sorted."""
        return sorted(set(names) - set(cls.__dataclass_fields__))

    def update(self, **values: Any) -> Self:
        """Set several fields, then check them together (so two bounds can move past each
        other), in place; a refused set leaves every field as it was. Returns the instance."""
        unknown = self.unknown_fields(values)
        if unknown:
            raise AttributeError(f"unknown {type(self).__name__} fields: {unknown}")
        before = {name: self.__dict__[name] for name in values}
        self.__dict__.update(values)
        try:
            self.__post_init__()
        except Exception:  # a ValueError, or a TypeError from a value of the wrong type
            self.__dict__.update(before)
            raise
        return self
