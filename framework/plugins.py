"""Plugin discovery: entry points, the SPLATRIG_PLUGINS variable, and the `python -m framework.plugins` listing.

Entry-point groups:
  splatrig.plugins  modules whose import registers components (ours are registered this way too)
  splatrig.configs  packages of YAML config groups, added to Hydra's search path
A plugin that fails to import is recorded with its traceback; it only breaks a run that asks for a name it would
have provided (the registry's "unknown name" error then shows the failure).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import pkgutil
import sys
import traceback
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from framework.registry import REGISTRIES, current_origin, set_discovery

ENV_VAR = "SPLATRIG_PLUGINS"
PLUGIN_GROUP = "splatrig.plugins"
CONFIG_GROUP = "splatrig.configs"
BUILTIN_DIST = "splatrig"


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
    """Import one plugin module, recording which distribution its registrations come from.

    When the import fails, the components it registered before failing are removed again: the module is gone from
    sys.modules, so they would be half-initialised, and a run selecting one must fail with the import error instead.
    """
    before = {kind: set(reg.names()) for kind, reg in REGISTRIES.items()}
    token = current_origin.set(origin)
    try:
        importlib.import_module(module)
    except Exception:
        _failures.append(PluginFailure(module, origin, traceback.format_exc()))
        for kind, reg in REGISTRIES.items():
            for name in set(reg.names()) - before[kind]:
                reg.unregister(name)
    finally:
        current_origin.reset(token)


def env_plugin_modules() -> list[str]:
    raw = os.environ.get(ENV_VAR, "")
    return [m.strip() for m in raw.replace(":", ",").split(",") if m.strip()]


def _builtins_first(ep: metadata.EntryPoint) -> tuple[bool, str, str]:
    """Our own components load first, so a third-party plugin that reuses one of their names is the one whose import
    fails (and is reported), never a whole built-in package."""
    dist = ep.dist.name if ep.dist is not None else ""
    return (dist != BUILTIN_DIST, dist, ep.name)


def load_plugins(force: bool = False) -> list[PluginFailure]:
    """Import every plugin once; returns the failures (also kept for error messages).

    `force` retries: modules that failed are imported again (Python keeps no half-imported module), modules that
    succeeded stay as they are.
    """
    global _loaded
    if _loaded and not force:
        return list(_failures)
    _loaded = True
    _failures.clear()
    for ep in sorted(metadata.entry_points(group=PLUGIN_GROUP), key=_builtins_first):
        origin = ep.dist.name if ep.dist is not None else "?"
        _import_as(ep.module, origin)
    for module in env_plugin_modules():
        _import_as(module, f"${ENV_VAR}")
    return list(_failures)


def failures() -> list[PluginFailure]:
    return list(_failures)


def failure_summary() -> str:
    return "\n".join(f.summary() for f in _failures)


class EntryPointDiscovery:
    """The registry's discovery hook: entry points and SPLATRIG_PLUGINS, imported once per process."""

    def discover(self) -> str:
        load_plugins()
        return failure_summary()


set_discovery(EntryPointDiscovery())


def import_submodules(package: str) -> None:
    """Import every module of `package` (used by the built-in plugin packages' __init__)."""
    pkg = sys.modules[package]
    for info in pkgutil.iter_modules(pkg.__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{package}.{info.name}")


def _conf_dir_of(module: str) -> Path | None:
    """The `conf/` folder of the nearest package containing `module` (`pkg.components` -> `pkg/conf`), if any.

    Only packages count: a single-file module has no folder of its own, and a `conf/` beside it belongs to whatever
    else lives in that directory (in a checkout of this repository, our own conf/).
    """
    parts = module.split(".")
    for i in range(len(parts), 0, -1):
        try:
            spec = importlib.util.find_spec(".".join(parts[:i]))
        except Exception:  # a package whose import raises: load_plugins reports it with its traceback
            return None
        for loc in (spec.submodule_search_locations or []) if spec is not None else []:
            conf = Path(loc) / "conf"
            if conf.is_dir():
                return conf
    return None


SWEEPS_PATH = "pkg://framework.sweeps"


def config_search_paths() -> list[str]:
    """Hydra search-path entries beyond conf/: our sweeps, then plugin config packages (entry points, then the conf/
    folders of SPLATRIG_PLUGINS packages).

    The sweeps folder is on the path so a sweep is a primary config chosen by name (`--config-name ablations`),
    installed or not; plugin configs add options to our groups (`densifier=example_prune_only`).
    """
    paths: list[str] = [SWEEPS_PATH]
    for ep in sorted(metadata.entry_points(group=CONFIG_GROUP), key=lambda e: e.name):
        paths.append(f"pkg://{ep.value}")
    for module in env_plugin_modules():
        conf = _conf_dir_of(module)
        if conf is not None and f"file://{conf}" not in paths:
            paths.append(f"file://{conf}")
    return paths


def component_table() -> list[tuple[str, str, str, str]]:
    """(kind, name, origin, availability) for every registered component, then one row per plugin that failed."""
    load_plugins()
    rows = []
    for kind, reg in REGISTRIES.items():
        for entry in reg:
            reason = entry.unavailable_reason()
            rows.append((kind, entry.name, entry.origin, "available" if reason is None else f"unavailable: {reason}"))
    for f in _failures:
        last = f.traceback.strip().splitlines()[-1] if f.traceback.strip() else "?"
        rows.append(("(plugin)", f.module, f.origin, f"import failed: {last} (traceback below)"))
    return rows


def format_table(rows: list[tuple[str, ...]], header: tuple[str, ...], pad: bool = True) -> str:
    """A Markdown table; `pad=False` leaves the columns unaligned (the same table, for files that are read rendered
    and would otherwise be mostly spaces)."""
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=False)] if pad else [0] * len(header)
    line = "| " + " | ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)) + " |"
    sep = "|" + "|".join("-" * (max(w, 1) + 2) for w in widths) + "|"
    body = ["| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)) + " |" for r in rows]
    return "\n".join([line, sep, *body])


def main() -> int:
    rows = component_table()
    print(format_table(rows, ("kind", "name", "origin", "status")))
    if _failures:
        print("\nPlugins that failed to import:")
        for f in _failures:
            print(f"\n--- {f.module} (from {f.origin}) ---\n{f.traceback}")
    paths = [p for p in config_search_paths() if p != SWEEPS_PATH]
    if paths:
        print("\nConfig search paths added by plugins: " + ", ".join(paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
