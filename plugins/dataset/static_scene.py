"""Dataset `static_scene`: multi-view images of a small textured mesh scene (no body), for the static Gaussian fit.

The images are rendered once by ray casting (framework.data.static_scene) and cached by a hash of the settings.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from framework.interfaces import MultiViewDataset
from framework.registry import register
from framework.types import Cameras, FrameBatch

_SPLITS = ("train", "novel_view", "novel_pose")


def _requires() -> str | None:
    try:
        import embreex  # noqa: F401
    except Exception as exc:  # pragma: no cover - depends on the install
        return f"embreex is needed to render the scene ({type(exc).__name__}: {exc}); pip install embreex"
    return None


@register("dataset", "static_scene", requires=_requires)
class StaticSceneDataset(MultiViewDataset):
    """Item i is view i of the split (B = 1, frame 0). `novel_pose` aliases `novel_view`: a static scene has one pose,
    so the held-out views are its only test set."""

    def __init__(
        self,
        root: str | None = None,
        split: str = "train",
        resolution: int = 128,
        num_train_views: int = 24,
        num_test_views: int = 6,
        seed: int = 0,
        supersample: int = 2,
    ) -> None:
        from PIL import Image

        from framework.data.static_scene import StaticSceneSettings, ensure_static_scene, load_meta

        if split not in _SPLITS:
            raise ValueError(f"dataset static_scene: unknown split '{split}'; expected one of {', '.join(_SPLITS)}.")
        settings = StaticSceneSettings(
            resolution=int(resolution),
            num_train_views=int(num_train_views),
            num_test_views=int(num_test_views),
            seed=int(seed),
            supersample=int(supersample),
        )
        self.path = ensure_static_scene(settings, root)
        meta = load_meta(self.path)
        cams = meta["cameras"]
        self.cameras = Cameras(
            K=torch.tensor(np.array([c["K"] for c in cams]), dtype=torch.float32),
            world_to_cam=torch.tensor(np.array([c["world_to_cam"] for c in cams]), dtype=torch.float32),
            width=int(meta["width"]),
            height=int(meta["height"]),
        )
        want = "train" if split == "train" else "test"
        self.split = split
        self.views = [i for i, c in enumerate(cams) if c["split"] == want]
        if not self.views:
            raise ValueError(
                f"dataset static_scene: split '{split}' has no views in {self.path / 'cameras.json'}; "
                f"set num_test_views >= 1."
            )
        self.frame_ids = [0]
        self.num_frames_total = 1
        self.body_name = None
        self.bounds = torch.tensor(meta["bounds"], dtype=torch.float32)  # [2, 3]
        # uint8 in memory: tiny at these sizes, decoded once
        self._images = [
            np.array(Image.open(Path(self.path) / "images" / f"{cams[v]['name']}.png").convert("RGB"))
            for v in self.views
        ]
        self._masks = [np.array(Image.open(Path(self.path) / "masks" / f"{cams[v]['name']}.png")) for v in self.views]

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, index: int) -> FrameBatch:
        if not 0 <= index < len(self):
            raise IndexError(f"static_scene[{self.split}]: index {index} out of range 0..{len(self) - 1}")
        v = self.views[index]
        image = torch.from_numpy(self._images[index]).float().div(255.0)[None]  # [1, H, W, 3]
        mask = torch.from_numpy(self._masks[index]).float().div(255.0)[None]  # [1, H, W]
        return FrameBatch(
            image=image,
            mask=mask,
            boundary=torch.ones_like(mask),
            cameras=self.cameras.index(v),
            frame=torch.zeros(1, dtype=torch.long),
            view=torch.tensor([v], dtype=torch.long),
        )
