"""Training logs scalars only on the steps Lightning writes to the logger: checked against Lightning's own decision."""

from __future__ import annotations

import lightning as L
import pytest
import torch

from framework.lightning.module import SplatModule


class _Tiny(L.LightningModule):
    """One parameter, manual optimisation (as SplatModule), recording when it would log."""

    def __init__(self) -> None:
        super().__init__()
        self.automatic_optimization = False
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.decisions: list[tuple[int, bool]] = []
        self.logged_steps: list[int] = []

    logs_this_step = SplatModule.logs_this_step

    def training_step(self, batch, batch_idx):
        log_now = self.logs_this_step()
        self.decisions.append((self.global_step, log_now))
        opt = self.optimizers()
        loss = (self.w - batch.mean()).square().sum()
        self.manual_backward(loss)
        opt.step()
        opt.zero_grad()
        if log_now:
            self.log("loss", loss.detach(), on_step=True, batch_size=1)

    def configure_optimizers(self):
        return torch.optim.SGD([self.w], lr=0.1)

    def train_dataloader(self):
        return torch.utils.data.DataLoader(torch.randn(64, 2), batch_size=1)


class _Reference(L.Callback):
    """Lightning's decision, read where it makes it (after the batch, before the step counter moves on)."""

    def __init__(self) -> None:
        self.writes: list[int] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if trainer._logger_connector.should_update_logs:
            self.writes.append(trainer.global_step - 1)  # the step that just ran


@pytest.mark.parametrize("every", [1, 3, 7])
def test_logs_exactly_on_the_steps_lightning_writes(tmp_path, every):
    module, ref = _Tiny(), _Reference()
    trainer = L.Trainer(
        max_steps=20,
        log_every_n_steps=every,
        callbacks=[ref],
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    trainer.fit(module)
    ours = [step for step, log_now in module.decisions if log_now]
    assert ours == ref.writes
    assert len(ours) == 20 // every
