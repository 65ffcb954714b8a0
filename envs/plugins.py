"""One registry of plug-in classes, shared by the environment suites (envs.suites) and the per-step probes
(harness.probes.registry): the built-ins named as "module:Class" and imported on first use, then the entry points of a
group of every installed distribution by name, then what registers at run time (this process only).

It sits at the lowest stage (envs/) so that both registries use it while envs/ imports nothing of harness/.
"""

from __future__ import annotations

import importlib
from contextlib import contextmanager
from importlib import metadata
from typing import Any, Callable, Iterator


class PluginRegistry:
    """Classes of one kind (a `base` subclass each, keyed by its `name`), in registration order.

    kind      what the messages call one ("probe", "suite")
    builtins  "module:Class" of the built-in ones, in order
    group     the entry-point group other distributions register under
    error     the ImportError subclass a class that cannot be loaded raises (one line naming it)
    make      what is kept for a class (the class itself, or an instance of it)
    check     a class's own checks at registration (a ValueError naming the problem), beyond its name
    """

    def __init__(self, kind: str, base: type, builtins: tuple[str, ...], group: str, error: type[ImportError],
                 make: Callable[[type], Any] = lambda cls: cls, check: Callable[[type], None] = lambda cls: None):
        self.kind, self.base, self.builtins, self.group, self.error = kind, base, builtins, group, error
        self.make, self.check = make, check
        self._classes: dict[str, type] = {}
        self._items: dict[str, Any] = {}
        self._loaded = False

    def load(self, target: str, origin: str) -> type:
        """The class "module:Class" names, imported (`origin` names where the name came from, for the message)."""
        module, _, attr = target.partition(":")
        try:
            cls = getattr(importlib.import_module(module), attr)
        except Exception as exc:  # noqa: BLE001 - any failure of a plug-in's import is named in one line
            raise self.error(f"the {self.kind} {origin} ({target}) cannot be loaded: {type(exc).__name__}: {exc}; "
                             "fix or uninstall the package that provides it") from None
        if not (isinstance(cls, type) and issubclass(cls, self.base)):
            raise self.error(f"the {self.kind} {origin} ({target}) is not a {self.base.__module__}."
                             f"{self.base.__qualname__} subclass")
        return cls

    def builtin(self) -> tuple[type, ...]:
        """The built-in classes, imported."""
        return tuple(self.load(target, "built-in") for target in self.builtins)

    def _load_all(self) -> None:
        """The built-ins, then every entry point of the group by name, registered once per process."""
        if self._loaded:
            return
        self._loaded = True
        found = [(cls, None) for cls in self.builtin()]
        for point in sorted(metadata.entry_points(group=self.group), key=lambda p: p.name):
            found.append((self.load(point.value, f"entry point {point.name!r}"), point.name))
        for cls, name in found:
            if name is not None and name != cls.name:
                raise self.error(f"the {self.kind} entry point {name!r} names a {self.kind} called {cls.name!r}; "
                                 "the two must be the same name")
            self.register(cls)

    def register(self, cls: type) -> type:
        """Add a class (usable as a decorator); another class under a taken name, or no name, is a ValueError."""
        self._load_all()
        if not cls.name or self._classes.get(cls.name, cls) is not cls:
            raise ValueError(f"a {self.kind} needs a name of its own; {cls.name!r} is taken or empty")
        self.check(cls)
        if cls.name not in self._items:
            self._classes[cls.name], self._items[cls.name] = cls, self.make(cls)
        return cls

    def unregister(self, name: str) -> None:
        self._classes.pop(name, None)
        self._items.pop(name, None)

    @contextmanager
    def registered(self, cls: type) -> Iterator[type]:
        """`cls` registered for the duration of the block (one defined outside the package, e.g. in a test)."""
        self.register(cls)
        try:
            yield cls
        finally:
            self.unregister(cls.name)

    def values(self) -> tuple:
        """What is kept for every registered class, in registration order."""
        self._load_all()
        return tuple(self._items.values())

    def get(self, name: str) -> Any:
        self._load_all()
        if name not in self._items:
            raise KeyError(f"no {self.kind} named {name!r}; registered: {', '.join(self._items)}")
        return self._items[name]
