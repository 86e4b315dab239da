"""Plugin discovery: entry points, the SPLATRIG_PLUGINS variable, and the `python -m framework.plugins` listing.

Entry-point groups:
  splatrig.plugins  modules whose import registers components (ours are registered this way too)
  splatrig.configs  packages of YAML config groups, added to Hydra's search path
A plugin that fails to import is recorded with its traceback; it only breaks a run that asks for a name it would
have provided (the registry's "unknown name" error then shows the failure).
"""

from __future__ import annotations

import importlib
import os
import pkgutil
import sys
import traceback
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from framework.registry import REGISTRIES, current_origin

ENV_VAR = "SPLATRIG_PLUGINS"
PLUGIN_GROUP = "splatrig.plugins"
CONFIG_GROUP = "splatrig.configs"


@dataclass(frozen=True)
class PluginFailure:
    module: str
    origin: str
    traceback: str

    def summary(self) -> str:
        last = self.traceback.strip().splitlines()[-1] if self.traceback.strip() else "?"
        return f"  {self.module} (from {self.origin}): {last}"


_loaded = False
_failures: list[PluginFailure] = []


def _import_as(module: str, origin: str) -> None:
    token = current_origin.set(origin)
    try:
        importlib.import_module(module)
    except Exception:
        _failures.append(PluginFailure(module, origin, traceback.format_exc()))
    finally:
        current_origin.reset(token)


def env_plugin_modules() -> list[str]:
    raw = os.environ.get(ENV_VAR, "")
    return [m.strip() for m in raw.replace(":", ",").split(",") if m.strip()]


def load_plugins(force: bool = False) -> list[PluginFailure]:
    """Import every plugin once; returns the failures (also kept for error messages)."""
    global _loaded
    if _loaded and not force:
        return list(_failures)
    _loaded = True
    for ep in sorted(metadata.entry_points(group=PLUGIN_GROUP), key=lambda e: (e.dist.name if e.dist else "", e.name)):
        origin = ep.dist.name if ep.dist is not None else "?"
        _import_as(ep.value.split(":")[0], origin)
    for module in env_plugin_modules():
        _import_as(module, f"${ENV_VAR}")
    return list(_failures)


def failures() -> list[PluginFailure]:
    return list(_failures)


def failure_summary() -> str:
    return "\n".join(f.summary() for f in _failures)


def import_submodules(package: str) -> None:
    """Import every module of `package` (used by the built-in plugin packages' __init__)."""
    pkg = sys.modules[package]
    for info in pkgutil.iter_modules(pkg.__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{package}.{info.name}")


def config_search_paths() -> list[str]:
    """Hydra search-path entries contributed by plugins (entry points, then SPLATRIG_PLUGINS packages' conf/)."""
    paths: list[str] = []
    for ep in sorted(metadata.entry_points(group=CONFIG_GROUP), key=lambda e: e.name):
        paths.append(f"pkg://{ep.value}")
    for module in env_plugin_modules():
        try:
            spec = importlib.util.find_spec(module.split(".")[0] if "." not in module else module)
        except (ImportError, ValueError):
            continue
        if spec is None or not spec.submodule_search_locations:
            continue
        for loc in spec.submodule_search_locations:
            conf = Path(loc) / "conf"
            if conf.is_dir():
                paths.append(f"file://{conf}")
    return paths


def component_table() -> list[tuple[str, str, str, str]]:
    """(kind, name, origin, availability) for every registered component."""
    load_plugins()
    rows = []
    for kind, reg in REGISTRIES.items():
        for entry in reg:
            reason = entry.unavailable_reason()
            rows.append((kind, entry.name, entry.origin, "available" if reason is None else f"unavailable: {reason}"))
    return rows


def format_table(rows: list[tuple[str, ...]], header: tuple[str, ...]) -> str:
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=False)]
    line = "| " + " | ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)) + " |"
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    body = ["| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)) + " |" for r in rows]
    return "\n".join([line, sep, *body])


def main() -> int:
    rows = component_table()
    print(format_table(rows, ("kind", "name", "origin", "status")))
    if _failures:
        print("\nPlugins that failed to import:")
        for f in _failures:
            print(f"\n--- {f.module} (from {f.origin}) ---\n{f.traceback}")
    paths = config_search_paths()
    if paths:
        print("\nExtra config search paths: " + ", ".join(paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
