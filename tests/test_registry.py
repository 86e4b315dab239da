"""Registries: registration rules, availability checks, and the messages a user sees for a wrong name.

Each test builds its own `Registry`, so nothing here leaks into the process-wide registries other tests use.
"""

from __future__ import annotations

import pytest

from framework import plugins
from framework.interfaces import BodyModel, Corrector, Deformer, Densifier, Loss, Metric, MultiViewDataset, Rasterizer
from framework.registry import (
    REGISTRIES,
    ComponentUnavailableError,
    DuplicateComponentError,
    Registry,
    RegistryError,
    UnknownComponentError,
    current_origin,
    origin_of,
    register,
)


class Base:
    def __init__(self, size: int = 1) -> None:
        self.size = size


def make_class(name: str, module: str = __name__, base: type = Base) -> type:
    """A fresh class whose identity (module, qualname) is chosen by the test, as if defined in another module."""
    return type(name, (base,), {"__module__": module, "__qualname__": name})


@pytest.fixture()
def reg(monkeypatch: pytest.MonkeyPatch) -> Registry[Base]:
    # Lookups of a missing name discover plugins first; here discovery is a no-op with no failures.
    monkeypatch.setattr(plugins, "_loaded", True)
    monkeypatch.setattr(plugins, "_failures", [])
    return Registry("widget", Base)


def test_register_build_and_entry_fields(reg: Registry[Base]) -> None:
    cls = reg.register("small")(make_class("Small"))
    obj = reg.build("small", size=7)
    assert type(obj) is cls and obj.size == 7
    assert cls.registry_name == "small"
    entry = reg.entry("small")
    assert entry.cls is cls and entry.name == "small" and entry.requires is None
    assert entry.unavailable_reason() is None
    assert reg.names() == ["small"] and "small" in reg and "big" not in reg


def test_origin_comes_from_discovery_then_from_the_installing_distribution(reg: Registry[Base]) -> None:
    token = current_origin.set("some-plugin-dist")
    try:
        reg.register("a")(make_class("A"))
    finally:
        current_origin.reset(token)
    assert reg.entry("a").origin == "some-plugin-dist"
    # Registered outside discovery: a class in the `plugins` package belongs to the splatrig distribution...
    builtin = make_class("Builtin", module="plugins.widget.builtin")
    assert origin_of(builtin) == "splatrig"
    reg.register("b")(builtin)
    assert reg.entry("b").origin == "splatrig"
    # ... and a class from a module no distribution installed is named by its module.
    reg.register("c")(make_class("C", module="not_installed_anywhere.mod"))
    assert reg.entry("c").origin == "not_installed_anywhere.mod"


def test_duplicate_name_from_another_class_is_rejected_naming_both(reg: Registry[Base]) -> None:
    first = make_class("First", module="pkg_one.widgets")
    second = make_class("Second", module="pkg_two.widgets")
    token = current_origin.set("dist-one")
    try:
        reg.register("shared")(first)
    finally:
        current_origin.reset(token)
    token = current_origin.set("dist-two")
    try:
        with pytest.raises(DuplicateComponentError) as info:
            reg.register("shared")(second)
    finally:
        current_origin.reset(token)
    msg = str(info.value)
    for part in ("widget 'shared'", "pkg_one.widgets.First", "dist-one", "pkg_two.widgets.Second", "dist-two"):
        assert part in msg, f"{part!r} missing from: {msg}"
    assert "Rename" in msg
    # A run that selects the contested name fails with the same message instead of silently taking the first class.
    with pytest.raises(DuplicateComponentError, match="registered twice"):
        reg.get("shared")
    # Other names are unaffected.
    reg.register("other")(make_class("Other"))
    assert reg.get("other").__name__ == "Other"


def test_same_class_registered_again_replaces_its_entry(reg: Registry[Base]) -> None:
    """A module imported twice (reload, or once by path and once by entry point) defines an equal class again."""
    old = reg.register("again")(make_class("Again", module="pkg.mod"))
    new = reg.register("again")(make_class("Again", module="pkg.mod"))
    assert old is not new and reg.get("again") is new


@pytest.mark.parametrize("thing", [make_class("Stranger", base=object), len, 3])
def test_non_subclass_is_rejected_naming_the_interface(reg: Registry[Base], thing: object) -> None:
    with pytest.raises(RegistryError) as info:
        reg.register("bad")(thing)  # type: ignore[arg-type]
    msg = str(info.value)
    assert "widget 'bad'" in msg and f"{__name__}.Base" in msg and "derive it from that interface" in msg
    assert "bad" not in reg


def test_requires_reason_makes_the_component_unavailable(reg: Registry[Base]) -> None:
    reg.register("gpu_only", requires=lambda: "gsplat: no CUDA device")(make_class("GpuOnly"))
    reg.register("always", requires=lambda: None)(make_class("Always"))
    assert reg.entry("gpu_only").unavailable_reason() == "gsplat: no CUDA device"
    with pytest.raises(ComponentUnavailableError) as info:
        reg.build("gpu_only")
    assert str(info.value) == "widget 'gpu_only' is not available here: gsplat: no CUDA device"
    assert isinstance(reg.build("always"), Base)


def test_requires_that_raises_is_reported_not_propagated(reg: Registry[Base]) -> None:
    def probe() -> str | None:
        raise RuntimeError("driver exploded")

    reg.register("flaky", requires=probe)(make_class("Flaky"))
    reason = reg.entry("flaky").unavailable_reason()
    assert reason == "availability check failed: RuntimeError: driver exploded"
    with pytest.raises(ComponentUnavailableError, match="driver exploded"):
        reg.get("flaky")


def test_unknown_name_lists_known_names_and_closest_match(reg: Registry[Base]) -> None:
    for name in ("torch_ref", "jax", "gsplat"):
        reg.register(name)(make_class(name.title().replace("_", "")))
    with pytest.raises(UnknownComponentError) as info:
        reg.get("torch_rf")
    msg = str(info.value)
    assert msg.startswith("unknown widget 'torch_rf'. Did you mean 'torch_ref'?")
    assert "Known widgets: gsplat, jax, torch_ref." in msg
    assert "python -m framework.plugins" in msg
    assert "failed to import" not in msg
    assert isinstance(info.value, KeyError)  # callers that catch KeyError keep working
    # Nothing close: no suggestion, still the list.
    with pytest.raises(UnknownComponentError) as info:
        reg.get("zzzzzz")
    assert "Did you mean" not in str(info.value) and "Known widgets: gsplat, jax, torch_ref." in str(info.value)


def test_unknown_name_in_empty_registry(reg: Registry[Base]) -> None:
    with pytest.raises(UnknownComponentError, match=r"Known widgets: \(none registered\)\."):
        reg.entry("anything")


def test_unknown_name_mentions_plugins_that_failed_to_import(reg: Registry[Base], monkeypatch) -> None:
    failure = plugins.PluginFailure(
        module="acme_widgets.components",
        origin="acme-widgets",
        traceback='Traceback (most recent call last):\n  File "x.py", line 1\nImportError: no module named acme_lib\n',
    )
    monkeypatch.setattr(plugins, "_failures", [failure])
    with pytest.raises(UnknownComponentError) as info:
        reg.get("acme_widget")
    msg = str(info.value)
    assert "Some plugins failed to import and may provide it:" in msg
    assert "acme_widgets.components (from acme-widgets): ImportError: no module named acme_lib" in msg


def test_missing_name_triggers_plugin_discovery_once(reg: Registry[Base], monkeypatch) -> None:
    """`REGISTRY.get(name)` works before anyone called load_plugins: a miss discovers plugins, then looks again."""
    calls = []

    def fake_load(force: bool = False) -> list:
        calls.append(force)
        if "late" not in reg:
            reg.register("late")(make_class("Late"))
        return []

    monkeypatch.setattr(plugins, "load_plugins", fake_load)
    assert reg.get("late").__name__ == "Late"
    assert calls == [False]
    reg.get("late")  # found directly: no second discovery
    assert calls == [False]


def test_register_rejects_unknown_kind_with_suggestion() -> None:
    with pytest.raises(RegistryError) as info:
        register("rasteriser", "x")
    msg = str(info.value)
    assert "unknown component kind 'rasteriser'" in msg and "Did you mean 'rasterizer'?" in msg
    assert "corrector" in msg and "metric" in msg


def test_one_registry_per_kind_with_its_interface() -> None:
    expected = {
        "rasterizer": Rasterizer,
        "corrector": Corrector,
        "deformer": Deformer,
        "loss": Loss,
        "densifier": Densifier,
        "body": BodyModel,
        "dataset": MultiViewDataset,
        "metric": Metric,
    }
    assert {k: r.base for k, r in REGISTRIES.items()} == expected
    assert all(r.kind == k for k, r in REGISTRIES.items())
