"""One vocabulary for dataset keys, the same in every dataset's config (conf/data/*.yaml):

- counts are `num_<things>`: `num_views`, `num_frames` (the studio), `num_train_views`, `num_test_views` (the static
  scene);
- view index lists are `<split>_views`: `train_views`, `test_views`, `novel_pose_views`;
- frame specs are `<split>_frames`: `train_frames`, `novel_pose_frames` ([start, end, step], end exclusive, or a list).

`RENAMED` holds the keys the rule replaced. Written by hand, an old key ends in one line naming the new one (on the
command line through `framework.cli`, anywhere else when the dataset is built: `split_config`); stored in a checkpoint
written before the rename, it is translated when the checkpoint is read (`upgrade_data_config`), so old runs still
evaluate and render.
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Iterable, Mapping
from typing import Any

#: old key -> its name under the rule (the synthetic studio's counts, before the rule)
RENAMED: dict[str, str] = {"views": "num_views", "frames": "num_frames"}
#: why, in the messages about an old key
RULE = "dataset counts are num_views / num_frames"


def old_key_hint(key: str, known: Iterable[str], prefix: str = "") -> str | None:
    """What to write instead of `key` when it is an old name (None otherwise): its new name when the dataset takes
    it, else the rule and the keys this dataset does take. `prefix`: how keys are written there ("data.")."""
    new = RENAMED.get(key)
    if new is None:
        return None
    known = list(known)
    if new in known:
        return f"it is now {prefix}{new} ({RULE})"
    return (
        f"the synthetic studio's {prefix}{key} is now {prefix}{new} ({RULE}); this dataset's keys are "
        f"{', '.join(known)}"
    )


def upgrade_data_config(data: Mapping[str, Any]) -> dict[str, Any]:
    """A stored `data` config with its old keys under their names now; a key whose new name is already there is
    left alone (the new one wins, as it would have when the checkpoint was written)."""
    out = dict(data)
    for old, new in RENAMED.items():
        if old in out and new not in out:
            out[new] = out.pop(old)
    return out


def split_config(config: Mapping[str, Any], *schemas: type, dataset: str) -> list[dict[str, Any]]:
    """The keys of a dataset's config dealt out to the dataclasses `schemas` by field name (a key both declare goes to
    the first), one dict per schema. A key none of them declares is a ValueError in one line: an old name says the
    new one, a near miss says the closest key, anything else lists the keys."""
    names = [{f.name for f in dataclasses.fields(s)} for s in schemas]
    known = sorted(set().union(*names))
    parts: list[dict[str, Any]] = [{} for _ in schemas]
    for key, value in config.items():
        owner = next((i for i, n in enumerate(names) if key in n), None)
        if owner is None:
            raise ValueError(f"{dataset}: {unknown_key_message(str(key), known)}")
        parts[owner][key] = value
    return parts


def unknown_key_message(key: str, known: list[str]) -> str:
    """What to say about a key a dataset does not take."""
    hint = old_key_hint(key, known)
    if hint is not None:
        return f"no key '{key}'; {hint}"
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    if close:
        return f"no key '{key}'; did you mean '{close[0]}'?"
    return f"no key '{key}'; its keys are {', '.join(known)}"
