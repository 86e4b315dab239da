"""Plugin discovery: our own entry points, the SPLATRIG_PLUGINS route, broken plugins, and the listing command.

Anything that imports plugins from a temporary folder runs `python -m framework.plugins` (or a short script) in a
fresh interpreter, exactly as a user would, so the process-wide registries of this test session stay untouched.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from importlib import metadata
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.errors import MissingConfigException

from framework import plugins

KINDS = ("rasterizer", "corrector", "deformer", "loss", "densifier", "body", "dataset", "metric")
HEADER = ["kind", "name", "origin", "status"]

GOOD_PLUGIN = '''
"""A plugin that is importable but not installed."""
from framework.interfaces import Densifier
from framework.registry import register


@register("densifier", "env_prune")
class EnvPrune(Densifier):
    def __init__(self, every: int = 10) -> None:
        self.every = every

    def initialize_state(self, scene_scale: float = 1.0) -> dict:
        return {}

    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        pass


@register("densifier", "env_needs_hardware", requires=lambda: "envplug: needs a quantum accelerator")
class EnvNeedsHardware(EnvPrune):
    pass
'''

BROKEN_PLUGIN = '''
"""Registers one component, then fails: the component must not survive the failed import."""
from framework.interfaces import Densifier
from framework.registry import register


@register("densifier", "env_broken")
class EnvBroken(Densifier):
    def initialize_state(self, scene_scale: float = 1.0) -> dict:
        return {}

    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        pass


def _load_table():
    raise RuntimeError("brokenplug cannot start: calibration table missing")


_load_table()
'''

DUPLICATE_PLUGIN = '''
"""Registers a fresh name, then takes the name of a built-in densifier."""
from framework.interfaces import Densifier
from framework.registry import DENSIFIERS, register


class Impostor(Densifier):
    def initialize_state(self, scene_scale: float = 1.0) -> dict:
        return {}

    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        pass


register("densifier", "env_dup_extra")(type("Extra", (Impostor,), {}))
register("densifier", min(e.name for e in DENSIFIERS if e.origin == "splatrig"))(Impostor)
'''


def write_package(root: Path, package: str, components: str, configs: dict[str, str] | None = None) -> Path:
    """`root/package/{__init__,components}.py` plus `conf/<group>/<option>.yaml` files; returns the package dir."""
    pkg = root / package
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text('"""Test plugin package."""\n')
    (pkg / "components.py").write_text(textwrap.dedent(components))
    for rel, text in (configs or {}).items():
        path = pkg / "conf" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return pkg


def plugin_env(tmp_path: Path, modules: str | None) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), *filter(None, [env.get("PYTHONPATH")])])
    env.pop(plugins.ENV_VAR, None)
    if modules is not None:
        env[plugins.ENV_VAR] = modules
    return env


def run_python(args: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL
    )


def parse_table(stdout: str) -> list[list[str]]:
    """Rows of the Markdown table that `python -m framework.plugins` prints first (header included)."""
    lines = []
    for line in stdout.splitlines():
        if not line.startswith("|"):
            if lines:
                break
            continue
        lines.append(line)
    assert len(lines) >= 2, f"no table in output:\n{stdout}"
    assert set(lines[1]) <= {"|", "-"}, f"second line is not a separator: {lines[1]!r}"
    rows = [[cell.strip() for cell in line.strip().strip("|").split("|")] for line in [lines[0], *lines[2:]]]
    assert all(len(r) == 4 for r in rows), rows
    assert len({len(line) for line in lines}) == 1, "columns are not aligned"
    return rows


def test_builtin_packages_are_declared_as_entry_points_of_the_splatrig_distribution() -> None:
    eps = [ep for ep in metadata.entry_points(group=plugins.PLUGIN_GROUP) if ep.dist and ep.dist.name == "splatrig"]
    assert sorted(ep.module for ep in eps) == sorted(f"plugins.{kind}" for kind in KINDS)


def test_builtin_components_come_from_the_splatrig_distribution(tmp_path: Path) -> None:
    """In a fresh interpreter, discovery alone (no direct import) registers the built-ins with origin `splatrig`."""
    script = textwrap.dedent(
        """
        import json, sys
        assert not any(m == "plugins" or m.startswith("plugins.") for m in sys.modules)
        from framework.plugins import load_plugins, failures
        from framework.registry import REGISTRIES
        load_plugins()
        rows = [(k, e.name, e.cls.__module__, e.origin) for k, r in REGISTRIES.items() for e in r]
        print(json.dumps({"rows": rows, "failures": [f.traceback for f in failures()]}))
        """
    )
    proc = run_python(["-c", script], plugin_env(tmp_path, None), tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["failures"] == [], "\n".join(out["failures"])
    builtin = [r for r in out["rows"] if r[2].startswith("plugins.")]
    assert builtin, "no built-in component registered through the entry points"
    wrong = [r for r in builtin if r[3] != "splatrig"]
    assert not wrong, f"built-ins with another origin than the splatrig distribution: {wrong}"
    for kind, _name, module, _origin in builtin:
        assert module.startswith(f"plugins.{kind}."), f"{module} registers a {kind} outside plugins/{kind}/"


def test_format_table_pads_columns() -> None:
    text = plugins.format_table([("loss", "l1", "splatrig", "available")], ("kind", "name", "origin", "status"))
    assert text.splitlines() == [
        "| kind | name | origin   | status    |",
        "|------|------|----------|-----------|",
        "| loss | l1   | splatrig | available |",
    ]


def test_listing_with_env_var_plugins_and_a_broken_one(tmp_path: Path) -> None:
    write_package(tmp_path, "envplug", GOOD_PLUGIN, {"densifier/env_prune.yaml": "name: env_prune\nevery: 25\n"})
    write_package(tmp_path, "brokenplug", BROKEN_PLUGIN)
    env = plugin_env(tmp_path, "envplug.components, brokenplug.components")
    proc = run_python(["-m", "framework.plugins"], env, tmp_path)
    assert proc.returncode == 0, proc.stderr
    rows = parse_table(proc.stdout)
    # Format: header, then one row per component grouped by kind, status "available" or "unavailable: <reason>".
    assert rows[0] == HEADER
    components = [r for r in rows[1:] if r[0] != "(plugin)"]
    kinds = [r[0] for r in components]
    assert set(kinds) <= set(KINDS) and kinds == sorted(kinds, key=KINDS.index), "rows are not grouped by kind"
    for _kind, name, origin, status in components:
        assert name and origin and (status == "available" or status.startswith("unavailable: ")), status
    assert ["densifier", "env_prune", "$SPLATRIG_PLUGINS", "available"] in rows
    assert [
        "densifier",
        "env_needs_hardware",
        "$SPLATRIG_PLUGINS",
        "unavailable: envplug: needs a quantum accelerator",
    ] in rows
    # The broken plugin: one row saying so, no component from it, and its full traceback below the table.
    broken = [r for r in rows if r[1] == "brokenplug.components"]
    assert broken == [
        [
            "(plugin)",
            "brokenplug.components",
            "$SPLATRIG_PLUGINS",
            "import failed: RuntimeError: brokenplug cannot start: calibration table missing (traceback below)",
        ]
    ]
    assert not any(r[1] == "env_broken" for r in rows)
    assert "--- brokenplug.components (from $SPLATRIG_PLUGINS) ---" in proc.stdout
    assert "Traceback (most recent call last):" in proc.stdout
    assert f"{tmp_path / 'brokenplug' / 'components.py'}" in proc.stdout and "_load_table()" in proc.stdout
    # The components of every other plugin are still there.
    assert any(r[2] == "splatrig" for r in rows[1:]), "built-in components disappeared next to a broken plugin"
    assert f"Config search paths added by plugins: file://{tmp_path / 'envplug' / 'conf'}" in proc.stdout


def test_selecting_a_component_of_a_broken_or_duplicate_plugin_fails_naming_it(tmp_path: Path) -> None:
    """Only runs that select it break: the build step every entry point uses names the failed plugin.

    `dupplug` reuses the name of a built-in densifier: its import fails (built-ins load first), and selecting the
    contested name fails naming both classes and distributions, since the user may have meant either.
    """
    write_package(tmp_path, "envplug", GOOD_PLUGIN)
    write_package(tmp_path, "brokenplug", BROKEN_PLUGIN)
    write_package(tmp_path, "dupplug", DUPLICATE_PLUGIN)
    script = textwrap.dedent(
        """
        import json
        from framework.build import build_component
        from framework.errors import SplatrigError
        from framework.plugins import load_plugins
        from framework.registry import DENSIFIERS

        failed = [f.module for f in load_plugins()]
        builtin = min(e.name for e in DENSIFIERS if e.origin == "splatrig")
        ok = build_component("densifier", {"name": "env_prune", "every": 3})
        errors = {}
        for name in ("env_broken", "env_dup_extra", builtin):
            try:
                build_component("densifier", {"name": name})
            except SplatrigError as exc:
                errors[name] = str(exc)
        print(json.dumps({"failed": failed, "ok": [type(ok).__name__, ok.every], "builtin": builtin, "errors": errors}))
        """
    )
    env = plugin_env(tmp_path, "envplug.components,brokenplug.components,dupplug.components")
    proc = run_python(["-c", script], env, tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["failed"] == ["brokenplug.components", "dupplug.components"]
    assert out["ok"] == ["EnvPrune", 3]
    errors = out["errors"]
    assert set(errors) == {"env_broken", "env_dup_extra", out["builtin"]}
    # A component of the broken module: unknown, and the message shows the import failure.
    err = errors["env_broken"]
    assert err.startswith("config group 'densifier': unknown densifier 'env_broken'."), err
    assert "Some plugins failed to import and may provide it:" in err
    assert "brokenplug.components (from $SPLATRIG_PLUGINS): RuntimeError: brokenplug cannot start" in err
    # What the duplicate module registered before failing is rolled back with it.
    assert "unknown densifier 'env_dup_extra'" in errors["env_dup_extra"]
    assert (
        "dupplug.components (from $SPLATRIG_PLUGINS): framework.registry.DuplicateComponentError:"
        in errors["env_dup_extra"]
    )
    # The contested name: both classes, both origins, and the fix.
    err = errors[out["builtin"]]
    assert f"densifier '{out['builtin']}' is registered twice" in err
    assert "(from splatrig)" in err and "dupplug.components.Impostor (from $SPLATRIG_PLUGINS)" in err
    assert "Rename one of them" in err


def test_env_var_accepts_commas_colons_and_blanks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(plugins.ENV_VAR, " a.b ,c:d.e,, ")
    assert plugins.env_plugin_modules() == ["a.b", "c", "d.e"]
    monkeypatch.delenv(plugins.ENV_VAR)
    assert plugins.env_plugin_modules() == []


def test_env_var_plugin_configs_join_hydra_search_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    package = f"envconf_{tmp_path.name.replace('-', '_')}"  # unique: this test imports it in-process
    write_package(
        tmp_path,
        package,
        "",
        {"densifier/env_prune.yaml": "name: env_prune\nevery: 25\n", "loss/env_l9.yaml": "name: env_l9\n"},
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(plugins.ENV_VAR, f"{package}.components")
    conf = tmp_path / package / "conf"
    assert plugins.config_search_paths()[-1] == f"file://{conf}"

    # The plugin's options join our groups in the training config: selected like any built-in option.
    with initialize_config_module("framework.conf", version_base="1.3"):
        cfg = compose("train", overrides=["+experiment=static_fit", "densifier=env_prune", "loss=env_l9"])
    assert dict(cfg.densifier) == {"name": "env_prune", "every": 25}
    assert dict(cfg.loss) == {"name": "env_l9"}

    monkeypatch.delenv(plugins.ENV_VAR)
    assert f"file://{conf}" not in plugins.config_search_paths()
    with initialize_config_module("framework.conf", version_base="1.3"):
        with pytest.raises(MissingConfigException, match="densifier/env_prune"):
            compose("train", overrides=["densifier=env_prune"])


def test_conf_dir_is_looked_up_in_packages_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A single-file plugin module has no conf/ of its own, even when a conf/ folder sits beside it."""
    (tmp_path / "conf").mkdir()
    module = f"single_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{module}.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert plugins._conf_dir_of(module) is None
    assert plugins._conf_dir_of("no_such_module_anywhere.components") is None
