"""Name -> component class registries, one per component kind.

A component is found by the name a config gives it (`rasterizer=torch_ref`), so a typo or a missing optional
dependency must produce one sentence that names the thing and the fix, never a traceback from deep inside a library.
"""

from __future__ import annotations

import difflib
import functools
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Generic, Protocol, TypeVar

from framework.errors import SplatrigError

T = TypeVar("T")

# Set by framework.plugins while a plugin module is imported, so each entry knows which distribution added it.
# Unset (None) when a module registers outside plugin discovery, e.g. a test imports a built-in directly; the origin
# is then inferred from the distribution that installed the class's top-level package.
current_origin: ContextVar[str | None] = ContextVar("splatrig_plugin_origin", default=None)


class Discovery(Protocol):
    """How components are found when a name is missing. The registry only knows this protocol; `framework.plugins`
    (entry points, SPLATRIG_PLUGINS) installs the implementation, so the registry never imports its discoverer."""

    def discover(self) -> str:
        """Import every plugin once (a no-op afterwards); return a summary of those that failed ("" if none)."""
        ...


_discovery: Discovery | None = None


def set_discovery(discovery: Discovery | None) -> None:
    """Install the hook `Registry.entry` calls on a miss (done by `framework.plugins` when it is imported)."""
    global _discovery
    _discovery = discovery


@functools.lru_cache(maxsize=1)
def _package_distributions() -> dict[str, list[str]]:
    return dict(metadata.packages_distributions())  # scans every installed distribution once (~0.2 s)


def origin_of(cls: type) -> str:
    """Where a class registered outside plugin discovery comes from: its distribution, else its module."""
    top = cls.__module__.split(".")[0]
    dists = _package_distributions().get(top)
    return dists[0] if dists else cls.__module__


class RegistryError(SplatrigError):
    """Base class of every error a registry raises; its message is meant for the user as it is."""


class UnknownComponentError(RegistryError, KeyError):
    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


class DuplicateComponentError(RegistryError):
    pass


class ComponentUnavailableError(RegistryError):
    pass


@dataclass(frozen=True)
class Entry(Generic[T]):
    name: str
    cls: type[T]
    origin: str
    requires: Callable[[], str | None] | None

    def unavailable_reason(self) -> str | None:
        """None when the component can run here, else a human reason ("gsplat: no CUDA device")."""
        if self.requires is None:
            return None
        try:
            return self.requires()
        except Exception as exc:  # an availability probe must never crash discovery
            return f"availability check failed: {type(exc).__name__}: {exc}"


class Registry(Generic[T]):
    """Components of one kind, registered with `@REGISTRY.register("name")`."""

    def __init__(self, kind: str, base: type[T]) -> None:
        self.kind = kind
        self.base = base
        self._entries: dict[str, Entry[T]] = {}
        # name -> message of a rejected second registration; selecting that name fails with it, since which of the
        # two classes a run would get depends on import order.
        self._conflicts: dict[str, str] = {}

    def register(self, name: str, requires: Callable[[], str | None] | None = None) -> Callable[[type[T]], type[T]]:
        """Class decorator. `requires` returns None when usable, else the reason it is not."""

        def decorator(cls: type[T]) -> type[T]:
            if not isinstance(cls, type) or not issubclass(cls, self.base):
                raise RegistryError(
                    f"{self.kind} '{name}': {getattr(cls, '__qualname__', cls)!r} is not a subclass of "
                    f"{self.base.__module__}.{self.base.__qualname__}; derive it from that interface."
                )
            origin = current_origin.get() or origin_of(cls)
            if name in self._entries:
                old = self._entries[name]
                # The same class seen again (a module re-imported or reloaded) replaces its entry.
                same = old.cls.__module__ == cls.__module__ and old.cls.__qualname__ == cls.__qualname__
                if not same:
                    msg = (
                        f"{self.kind} '{name}' is registered twice: by {old.cls.__module__}.{old.cls.__qualname__} "
                        f"(from {old.origin}) and by {cls.__module__}.{cls.__qualname__} (from {origin}). "
                        f"Rename one of them, or uninstall the plugin that should not provide it."
                    )
                    self._conflicts[name] = msg
                    raise DuplicateComponentError(msg)
            self._entries[name] = Entry(name=name, cls=cls, origin=origin, requires=requires)
            cls.registry_name = name  # type: ignore[attr-defined]
            return cls

        return decorator

    def unregister(self, name: str) -> None:
        """Forget `name`; plugin discovery uses it to undo what a module registered before its import failed."""
        self._entries.pop(name, None)
        self._conflicts.pop(name, None)

    def names(self) -> list[str]:
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[Entry[T]]:
        return iter(self._entries[n] for n in self.names())

    def entry(self, name: str) -> Entry[T]:
        """The entry registered as `name`; plugins are discovered first (through the installed discovery hook) if
        that has not happened yet."""
        if name not in self._entries:
            failures = _discovery.discover() if _discovery is not None else ""
            if name not in self._entries:
                raise UnknownComponentError(self._unknown_message(name, failures))
        if name in self._conflicts:
            raise DuplicateComponentError(self._conflicts[name])
        return self._entries[name]

    def get(self, name: str) -> type[T]:
        """The class registered as `name`, after checking it can run here."""
        entry = self.entry(name)
        reason = entry.unavailable_reason()
        if reason is not None:
            raise ComponentUnavailableError(f"{self.kind} '{name}' is not available here: {reason}")
        return entry.cls

    def build(self, name: str, /, **kwargs: Any) -> T:
        return self.get(name)(**kwargs)

    def _unknown_message(self, name: str, failures: str) -> str:
        known = self.names()
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.5)
        msg = f"unknown {self.kind} '{name}'."
        if close:
            msg += f" Did you mean '{close[0]}'?"
        msg += f" Known {self.kind}s: {', '.join(known) if known else '(none registered)'}."
        msg += " List every component with `python -m framework.plugins`."
        if failures:
            msg += f"\nSome plugins failed to import and may provide it:\n{failures}"
        return msg


def _registries() -> dict[str, Registry[Any]]:
    from framework.interfaces import (
        BodyModel,
        Corrector,
        Deformer,
        Densifier,
        Loss,
        Metric,
        MultiViewDataset,
        Rasterizer,
    )

    return {
        "rasterizer": Registry("rasterizer", Rasterizer),
        "corrector": Registry("corrector", Corrector),
        "deformer": Registry("deformer", Deformer),
        "loss": Registry("loss", Loss),
        "densifier": Registry("densifier", Densifier),
        "body": Registry("body", BodyModel),
        "dataset": Registry("dataset", MultiViewDataset),
        "metric": Registry("metric", Metric),
    }


REGISTRIES: dict[str, Registry[Any]] = _registries()
RASTERIZERS = REGISTRIES["rasterizer"]
CORRECTORS = REGISTRIES["corrector"]
DEFORMERS = REGISTRIES["deformer"]
LOSSES = REGISTRIES["loss"]
DENSIFIERS = REGISTRIES["densifier"]
BODIES = REGISTRIES["body"]
DATASETS = REGISTRIES["dataset"]
METRICS = REGISTRIES["metric"]


def registry(kind: str) -> Registry[Any]:
    if kind not in REGISTRIES:
        close = difflib.get_close_matches(kind, list(REGISTRIES), n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        raise RegistryError(f"unknown component kind '{kind}'.{hint} Kinds: {', '.join(REGISTRIES)}.")
    return REGISTRIES[kind]


def register(kind: str, name: str, requires: Callable[[], str | None] | None = None) -> Callable[[type], type]:
    """`@register("rasterizer", "torch_ref")`: the one decorator plugins use."""
    return registry(kind).register(name, requires=requires)
