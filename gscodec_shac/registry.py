"""One registry idiom for everything found by name (SH stages, grid codecs, RD recipes).

A :class:`Registry` maps names to classes (or, for stateless helpers such as RD
recipes, instances). They join with :meth:`Registry.register`, a decorator (their
``name`` attribute is the key); the built-in ones are imported on
first use, so looking one up stays cheap and a module that needs torch is only imported
when asked for. Adding one is a new module in the folder plus its name in the
registry's ``builtin`` list.

``builtin`` may also map each built-in name to the one module that registers it: then
checking a name (:meth:`Registry.names`, ``in``) imports nothing and :meth:`Registry.get`
imports only that name's module, so reading a stream's header does not load the image
libraries of codecs it does not use.
"""

from __future__ import annotations

import importlib
from typing import Generic, Iterator, Mapping, Sequence, TypeVar

from gscodec_shac.errors import GscodecError, ValidationError

T = TypeVar("T")


class Registry(Generic[T]):
    """Classes of one ``kind`` by name; ``builtin`` modules (under ``package``) register on first use."""

    def __init__(self, kind: str, package: str, builtin: Sequence[str] | Mapping[str, str],
                 error: type[GscodecError] = ValidationError) -> None:
        self.kind = kind
        self.package = package
        self.modules: dict[str, str] = dict(builtin) if isinstance(builtin, Mapping) else {}
        self.builtin = tuple(dict.fromkeys(self.modules.values())) if self.modules else tuple(builtin)
        self.error = error
        self._classes: dict[str, type[T]] = {}
        self._loaded = False

    def register(self, cls: type[T]) -> type[T]:
        """Class decorator: add ``cls`` under ``cls.name``."""
        name = getattr(cls, "name")
        if name in self._classes and self._classes[name] is not cls:
            raise ValueError(f"{self.kind} {name!r} is registered twice")
        self._classes[name] = cls
        return cls

    def get(self, name: str) -> type[T]:
        """The class called ``name``; an error naming the known ones otherwise."""
        if isinstance(name, str) and name in self.modules:
            importlib.import_module(f"{self.package}.{self.modules[name]}")
        else:
            self._load()
        if not isinstance(name, str) or name not in self._classes:
            raise self.error(f"unknown {self.kind} {name!r}; known: {', '.join(self.names())}")
        return self._classes[name]

    def names(self) -> list[str]:
        """Every registered name, sorted."""
        if not self.modules:
            self._load()
        return sorted(set(self._classes) | set(self.modules))

    def __contains__(self, name: object) -> bool:
        if isinstance(name, str) and name in self.modules:
            return True
        self._load()
        return name in self._classes

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def items(self) -> list[tuple[str, type[T]]]:
        self._load()
        return sorted(self._classes.items())

    def _load(self) -> None:
        if self._loaded:
            return
        for module in self.builtin:
            importlib.import_module(f"{self.package}.{module}")
        self._loaded = True
