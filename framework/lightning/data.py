"""DataModule: train / validation / evaluation splits of one multi-view sequence, as FrameBatches."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import lightning as L
import torch
from torch.utils.data import DataLoader, Sampler

from framework.errors import SplatrigError
from framework.interfaces import MultiViewDataset
from framework.types import Cameras, FrameBatch


def collate_frames(items: Sequence[FrameBatch]) -> FrameBatch:
    """Stack B=1 samples along the batch axis (cameras too)."""
    if len(items) == 1:
        return items[0]

    def cat(name: str) -> torch.Tensor | None:
        values = [getattr(i, name) for i in items]
        return None if values[0] is None else torch.cat(values)

    first = items[0].cameras
    cams = Cameras(
        K=torch.cat([i.cameras.K for i in items]),
        world_to_cam=torch.cat([i.cameras.world_to_cam for i in items]),
        width=first.width,
        height=first.height,
    )
    return FrameBatch(
        image=cat("image"),
        mask=cat("mask"),
        boundary=cat("boundary"),
        cameras=cams,
        frame=cat("frame"),
        pose=cat("pose"),
        root=cat("root"),
        betas=cat("betas"),
        view=cat("view"),
    )


class StepSampler(Sampler[int]):
    """Training order as a function of the step: item k of the run is drawn (with replacement) from a block of
    indices seeded by (seed, k // block), whatever epoch or process asks for it.

    A resumed run asks `start()` (the trainer's step count) where to continue, so it sees the frames the
    uninterrupted run would have seen, and no draw touches the global RNG (which the checkpoint restores for the
    model's own randomness)."""

    def __init__(
        self, n: int, seed: int, start: Callable[[], int] = lambda: 0, num_samples: int = 1000, block: int = 1024
    ) -> None:
        self.n, self.seed, self.start, self.num_samples, self.block = n, seed, start, num_samples, block

    def indices(self, first: int, count: int) -> list[int]:
        """The items of positions first .. first + count - 1."""
        out: list[int] = []
        k = first
        while len(out) < count:
            b = k // self.block
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + b)
            drawn = torch.randint(self.n, (self.block,), generator=g).tolist()
            take = min(count - len(out), (b + 1) * self.block - k)
            out += drawn[k - b * self.block : k - b * self.block + take]
            k += take
        return out

    def __iter__(self) -> Iterator[int]:
        return iter(self.indices(int(self.start()), self.num_samples) if self.n else [])

    def __len__(self) -> int:
        return self.num_samples if self.n else 0


class StepLoader(DataLoader):
    """The training loader: its position is the trainer's step (`StepSampler`), so its resumable state is the
    sampler's seed and that step. Lightning saves it in every checkpoint and hands it back on resume; a checkpoint of
    another frame order (another seed or dataset size) is refused rather than continued silently."""

    def state_dict(self) -> dict[str, int]:
        sampler = self.sampler
        return {"seed": int(sampler.seed), "items": int(sampler.n), "step": int(sampler.start())}

    def load_state_dict(self, state: dict[str, int]) -> None:
        sampler = self.sampler
        if (state.get("seed"), state.get("items")) != (sampler.seed, sampler.n):
            raise SplatrigError(
                f"resume: the checkpoint's frame order (seed {state.get('seed')}, {state.get('items')} training "
                f"images) is not this run's (seed {sampler.seed}, {sampler.n}); resume with the first run's seed and "
                f"data overrides."
            )


class FrameDataModule(L.LightningDataModule):
    """Holds already-built split datasets; the model needs the train split's metadata before the trainer starts."""

    def __init__(
        self,
        build_split: Callable[[str], MultiViewDataset],
        val_split: str = "novel_view",
        val_max_items: int = 8,
        num_workers: int = 0,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.build_split = build_split
        self.val_split = val_split
        self.val_max_items = val_max_items
        self.num_workers = num_workers
        self.seed = seed
        self._splits: dict[str, MultiViewDataset] = {}

    def split(self, name: str) -> MultiViewDataset:
        if name not in self._splits:
            self._splits[name] = self.build_split(name)
        return self._splits[name]

    @property
    def train_set(self) -> MultiViewDataset:
        return self.split("train")

    def _loader(self, dataset: torch.utils.data.Dataset, sampler=None, shuffle: bool = False) -> DataLoader:
        loader = StepLoader if isinstance(sampler, StepSampler) else DataLoader
        return loader(
            dataset,
            batch_size=1,
            sampler=sampler,
            shuffle=shuffle,
            num_workers=self.num_workers,
            collate_fn=collate_frames,
            # page-locked batches (FrameBatch.pin_memory) reach a GPU without the host waiting for the copy
            pin_memory=torch.cuda.is_available(),
            persistent_workers=self.num_workers > 0,
            generator=torch.Generator().manual_seed(self.seed),  # worker seeds drawn here, not from the global RNG
        )

    def _trained_steps(self) -> int:
        trainer = getattr(self, "trainer", None)
        return int(trainer.global_step) if trainer is not None else 0

    def transfer_batch_to_device(self, batch, device: torch.device, dataloader_idx: int):
        """A FrameBatch goes to the device with `non_blocking`: its tensors are page-locked on a CUDA machine (the
        DataLoader pins them), so the host queues the step while the copy runs. Lightning passes `non_blocking` only
        to plain tensors, not to the objects it moves with their own `to`."""
        if isinstance(batch, FrameBatch):
            return batch.to(device, non_blocking=device.type == "cuda")
        return super().transfer_batch_to_device(batch, device, dataloader_idx)

    def train_dataloader(self) -> DataLoader:
        # A long epoch: validation and checkpoints run on step counts, and a resumed run continues the step count and
        # the order of frames (StepSampler).
        sampler = StepSampler(len(self.train_set), self.seed, self._trained_steps, max(len(self.train_set), 1000))
        return self._loader(self.train_set, sampler=sampler)

    def val_dataloader(self) -> DataLoader:
        dataset = self.split(self.val_split)
        n = len(dataset)
        take = min(n, self.val_max_items)
        idx = torch.linspace(0, n - 1, take).round().long().unique().tolist() if n else []
        return self._loader(torch.utils.data.Subset(dataset, idx))
