"""The Hydra entry points' command line: an override Hydra cannot compose (an unknown option of a config group, an
unknown experiment, an unknown key) ends in one `error: ...` line with a did-you-mean and exit status 2, like
splatrig's own errors (framework.errors), instead of Hydra's report and exit status 1. A dataset key renamed by the
naming rule (framework.dataset_keys) names its new name.

`@hydra_main("train")` stands for `@hydra.main(version_base="1.3", config_path="pkg://framework.conf",
config_name="train")`. Hydra reports its errors itself (`run_and_report`: message, `sys.exit(1)`) unless
HYDRA_FULL_ERROR=1, which makes it raise them: that is set while Hydra composes, so its composition errors reach us
with their details (the group's options, the key's parent), and unset again when the job starts, so the job's own
errors are reported as before. HYDRA_FULL_ERROR=1 or SPLATRIG_FULL_ERROR=1 set by the user keeps Hydra's report.
"""

from __future__ import annotations

import difflib
import functools
import os
import sys
from collections.abc import Callable
from typing import Any

CONFIG_PATH = "pkg://framework.conf"
_RAISE = "HYDRA_FULL_ERROR"
_raising = False  # whether we set HYDRA_FULL_ERROR (and so unset it when the job starts)


def did_you_mean(name: str, valid: list[str]) -> str:
    """'; did you mean X?' for the closest valid name, or ''."""
    close = difflib.get_close_matches(name, valid, n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


def composition_message(exc: BaseException) -> str:
    """One line for an error Hydra raised while composing the config."""
    from hydra.errors import MissingConfigException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, ValidationError

    from framework.dataset_keys import old_key_hint

    if isinstance(exc, MissingConfigException) and exc.options and exc.missing_cfg_file:
        group, _, name = str(exc.missing_cfg_file).rpartition("/")
        options = sorted(exc.options)
        hint = did_you_mean(name, options) or "."
        return f"{group}={name}: no such option in group '{group}'{hint} Options: {', '.join(options)}"
    cause = exc.__cause__
    if isinstance(cause, ValidationError) and cause.full_key:  # a value of the wrong type (framework.config_schema)
        return f"{cause.full_key}: expected {expected_type(cause)}, got {_shown(getattr(cause, 'value', None))}"
    parent = getattr(cause, "parent_node", None)
    if isinstance(cause, ConfigAttributeError | ConfigKeyError) and cause.full_key and hasattr(parent, "keys"):
        key = str(cause.full_key)
        prefix, _, leaf = key.rpartition(".")
        dotted = f"{prefix}." if prefix else ""
        names = [str(k) for k in parent.keys()]
        renamed = old_key_hint(leaf, names, dotted) if prefix == "data" else None  # data.views -> data.num_views
        if renamed is not None:
            return f"{key}: no such key; {renamed}"
        close = difflib.get_close_matches(leaf, names, n=1, cutoff=0.6)
        if close:
            return f"{key}: no such key; did you mean {dotted}{close[0]}?"
        # no near miss: perhaps a new key on purpose
        return (
            f"{key}: no such key; the keys of {prefix or 'the config'} are {', '.join(names)} (+{key}=VALUE adds one)"
        )
    lines = [line.strip() for line in str(exc).splitlines()]
    if cause is not None:
        lines += [line.strip() for line in str(cause).splitlines()[:1]]
    kept = [line for line in lines if line and not line.startswith(("Config search path", "provider="))]
    return " ".join(kept)


_TYPE_WORDS = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def expected_type(cause: Any) -> str:
    """The type a typed config key takes, in words, from the schema dataclass (or typed list) OmegaConf names."""
    import typing

    kind: Any = None
    owner, key = getattr(cause, "object_type", None), getattr(cause, "key", None)
    if isinstance(key, str) and isinstance(owner, type):
        try:
            kind = typing.get_type_hints(owner).get(key)
        except (NameError, TypeError):
            kind = None
    elif isinstance(key, int):  # an item of a typed list
        kind = next(iter(typing.get_args(getattr(cause, "ref_type", None))), None)
    args = typing.get_args(kind)
    optional = type(None) in args
    if optional:
        kind = next(a for a in args if a is not type(None))
    origin = typing.get_origin(kind)
    if origin in (list, tuple):
        inner = typing.get_args(kind)
        word = f"a list of {_TYPE_WORDS.get(inner[0], 'values').split(' ', 1)[-1]}s" if inner else "a list"
    elif origin is dict:
        word = "a mapping (key: value)"
    else:
        word = _TYPE_WORDS.get(kind, getattr(kind, "__name__", "another type"))
    return f"{word} or null" if optional else word


def _shown(value: Any) -> str:
    return "null" if value is None else repr(value)


def hydra_main(config_name: str) -> Callable[[Callable[[Any], Any]], Callable[[], Any]]:
    """`@hydra.main` of the config `config_name` in framework/conf, its composition errors reported in one line."""

    def decorate(task: Callable[[Any], Any]) -> Callable[[], Any]:
        import hydra

        @functools.wraps(task)  # Hydra names the job after the wrapped function's module
        def job(cfg: Any) -> Any:
            global _raising
            if _raising:
                os.environ.pop(_RAISE, None)
                _raising = False
            return task(cfg)

        composed = hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name=config_name)(job)

        @functools.wraps(task)
        def main() -> Any:
            global _raising
            if os.environ.get(_RAISE) or os.environ.get("SPLATRIG_FULL_ERROR"):
                return composed()
            from hydra.errors import HydraException
            from omegaconf.errors import OmegaConfBaseException

            os.environ[_RAISE], _raising = "1", True
            try:
                return composed()
            except (HydraException, OmegaConfBaseException) as exc:
                if not _raising:  # raised after the job started: not ours to reword
                    raise
                print(f"error: {composition_message(exc)}", file=sys.stderr)
                sys.exit(2)
            finally:
                if _raising:
                    os.environ.pop(_RAISE, None)
                    _raising = False

        return main

    return decorate
