"""Turn config nodes into components through the registries.

A component node is `{name: <registry name>, **constructor kwargs}`; `name: null` means "no component" (e.g. no body
for a static scene). Errors name the config group and list the options, so a typo never surfaces from deep inside
Hydra or a constructor.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from framework.errors import SplatrigError
from framework.plugins import load_plugins
from framework.registry import RegistryError, registry


class ConfigError(SplatrigError):
    """A config value that cannot be turned into a component; the message says which key and how to fix it."""


def node_kwargs(node: DictConfig | dict[str, Any] | None) -> tuple[str | None, dict[str, Any]]:
    if node is None:
        return None, {}
    data = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node)
    assert isinstance(data, dict)
    name = data.pop("name", None)
    return name, data


def build_component(kind: str, node: DictConfig | dict[str, Any] | None, group: str | None = None, **extra: Any) -> Any:
    """Build the `kind` component described by `node` (None when its name is null)."""
    load_plugins()
    group = group or kind
    name, kwargs = node_kwargs(node)
    if name is None:
        return None
    kwargs.update(extra)
    reg = registry(kind)
    try:
        cls = reg.get(name)
    except RegistryError as exc:
        raise ConfigError(f"config group '{group}': {exc}") from None
    try:
        return cls(**kwargs)
    except SplatrigError:
        raise
    except (ValueError, FileNotFoundError) as exc:  # components reject bad values / missing files by name
        raise ConfigError(f"config group '{group}' ({kind} '{name}'): {exc}") from None
    except TypeError as exc:
        raise ConfigError(
            f"config group '{group}' ({kind} '{name}'): {exc}. Check the keys in conf/{group}/{name}.yaml or your "
            f"command-line overrides against {cls.__module__}.{cls.__qualname__}."
        ) from None


def with_fitted_betas(body_node: DictConfig | dict[str, Any] | None, betas: list[float] | None) -> dict | None:
    """The body node with `betas` filled from the data when the body takes betas and the config leaves them null, so
    an SMPL-family body gets the shape the capture's poses were fitted with."""
    if body_node is None:
        return None
    node = OmegaConf.to_container(body_node, resolve=True) if isinstance(body_node, DictConfig) else dict(body_node)
    if betas is None or "betas" not in node or node["betas"] is not None:
        return node
    return {**node, "betas": [float(b) for b in betas]}


SPLIT_OVERRIDES = "split_overrides"


def build_split(data_cfg: DictConfig | dict[str, Any], split: str) -> Any:
    """The dataset of one split from a run's `data` config. `data.split_overrides` maps a split to dataset keys that
    differ for it alone: `{train: {downscale: 2}}` trains on half-size images and evaluates on the full-size ones, so
    every run of a comparison is measured against the same ground truth."""
    name, node = node_kwargs(data_cfg)
    node["name"] = name
    overrides = (node.pop(SPLIT_OVERRIDES, None) or {}).get(split) or {}
    return build_component("dataset", {**node, **overrides}, group="data", split=split)
