"""Finding and reading SMPL / SMPL-X model files: the names their licensors ship them under, the error that says where
to get them, and raw arrays such as SMPL-X's hand PCA bases (which EasyMocap's 87-value poses need)."""

from __future__ import annotations

import importlib.util
import pickle
from pathlib import Path

import numpy as np

from framework.errors import SplatrigError

LICENSORS = {"smpl": "https://smpl.is.tue.mpg.de", "smplx": "https://smpl-x.is.tue.mpg.de"}


class BodyModelFileMissing(SplatrigError, FileNotFoundError):
    """The SMPL / SMPL-X model file is not where the config points; the message names the file and its licensor."""


def smplx_requirement() -> str | None:
    """None when the `smplx` package is importable, else why the SMPL-family bodies cannot run."""
    if importlib.util.find_spec("smplx") is None:
        return "the `smplx` package is not installed (pip install smplx)"
    return None


def expected_filename(model_type: str, gender: str, ext: str | None = None) -> str:
    prefix = {"smpl": "SMPL", "smplx": "SMPLX"}[model_type]
    ext = ext or ("pkl" if model_type == "smpl" else "npz")
    return f"{prefix}_{gender.upper()}.{ext}"


def resolve_model_file(model_path: str | Path | None, model_type: str = "smpl", gender: str = "neutral") -> Path:
    """The model file for `model_path` (a file, or a folder holding it directly or under `<model_type>/`).

    Raises BodyModelFileMissing (a FileNotFoundError) naming the expected file, every path tried, and where to
    obtain it."""
    if model_type not in LICENSORS:
        raise ValueError(f"{model_type} body: model_type must be one of {sorted(LICENSORS)}; got {model_type!r}.")
    if gender.lower() not in ("neutral", "male", "female"):
        raise ValueError(f"{model_type} body: gender must be neutral, male or female; got {gender!r}.")
    names = [expected_filename(model_type, gender)]
    if model_type == "smplx":
        names.append(expected_filename(model_type, gender, "pkl"))
    tried: list[Path] = []
    if model_path not in (None, ""):
        path = Path(str(model_path)).expanduser()
        if path.suffix in (".pkl", ".npz"):
            tried.append(path)
        else:
            tried += [path / n for n in names] + [path / model_type / n for n in names]
    for candidate in tried:
        if candidate.is_file():
            return candidate
    where = ", ".join(f"'{p}'" for p in tried) if tried else "nowhere (body.model_path is not set)"
    raise BodyModelFileMissing(
        f"{model_type} body: the {model_type.upper()} model file '{names[0]}' was not found; tried {where}. "
        f"Its licence forbids redistribution, so it is not shipped with splatrig: register with its licensor at "
        f"{LICENSORS[model_type]}, download the model, and pass body.model_path=/path/to/{names[0]} "
        f"(or the folder that holds it)."
    )


def load_model_arrays(path: Path) -> dict:
    """The raw arrays of a model file (.npz, or a .pkl of numpy arrays), without building a model."""
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=True) as data:
            return {k: data[k] for k in data.files}
    with open(path, "rb") as fh:
        return dict(pickle.load(fh, encoding="latin1"))


def hand_pca_components(path: Path, num_comps: int) -> tuple[np.ndarray, np.ndarray]:
    """Left and right hand PCA bases [num_comps, 45] of an SMPL-X file (`hands_components{l,r}`, first rows)."""
    data = load_model_arrays(path)
    if "hands_componentsl" not in data or "hands_componentsr" not in data:
        raise SplatrigError(
            f"{path}: expected an SMPL-X model file with hand PCA bases 'hands_componentsl' / 'hands_componentsr', "
            f"found keys {sorted(data)[:12]}; point body.model_path at SMPLX_<GENDER>.pkl or .npz."
        )
    left = np.asarray(data["hands_componentsl"], dtype=np.float64)[:num_comps]
    right = np.asarray(data["hands_componentsr"], dtype=np.float64)[:num_comps]
    return left, right
