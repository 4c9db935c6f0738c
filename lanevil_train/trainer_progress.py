"""Lightning progress displays for `progress=`: rich bars on a terminal, plain periodic lines in logs and pipes."""

from __future__ import annotations

import pytorch_lightning as pl
from pytorch_lightning.callbacks import ProgressBar, RichProgressBar, TQDMProgressBar

from lanevil_train.progress import PlainProgress, resolve_mode


class StepRichProgressBar(RichProgressBar):
    """Lightning's rich bar, with a step-bounded run (max_epochs=-1, max_steps=N) shown as such, not 'Epoch 7/-2'."""

    def _get_train_description(self, current_epoch: int) -> str:
        trainer = self.trainer
        if trainer.max_steps > 0 and (trainer.max_epochs is None or trainer.max_epochs < 0):
            return f"Epoch {current_epoch} (to step {trainer.max_steps})"
        return super()._get_train_description(current_epoch)


def _format(metrics: dict) -> str:
    return " ".join(f"{key} {value:.4g}" if isinstance(value, float) else f"{key} {value}"
                    for key, value in metrics.items() if key != "v_num")


class LineProgressBar(ProgressBar):
    """Plain lines for logs: training step/total, loss, rate and ETA at the first step and then every `interval`
    seconds; a long validation or test every `interval` seconds too, the test's end, and the validation scores
    when a validation ends. Rank 0 only."""

    def __init__(self, interval: float = 30.0):
        super().__init__()
        self.interval = interval
        self.enabled = True
        self._train: PlainProgress | None = None
        self._eval: PlainProgress | None = None

    def disable(self) -> None:
        self.enabled = False

    def enable(self) -> None:
        self.enabled = True

    def _active(self, trainer: pl.Trainer) -> bool:
        return self.enabled and trainer.is_global_zero and not trainer.sanity_checking

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        total = trainer.estimated_stepping_batches
        self._train = PlainProgress(total, trainer.global_step, "train", "steps", self.interval)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch, batch_idx: int):
        if self._active(trainer) and self._train is not None:
            note = f"epoch {trainer.current_epoch} {_format(self.get_metrics(trainer, pl_module))}".strip()
            self._train.update(trainer.global_step - self._train.done, note)

    def _start_eval(self, desc: str, totals, last_line: bool) -> None:
        total = sum(t for t in totals if t < float("inf")) if totals else 0
        self._eval = PlainProgress(int(total), 0, desc, "batches", self.interval, first_line=False,
                                   last_line=last_line)

    def on_validation_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._active(trainer):  # a validation's end is its scores line (on_validation_end)
            self._start_eval("validation", trainer.num_val_batches, last_line=False)

    def on_test_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._active(trainer):
            self._start_eval("test", trainer.num_test_batches, last_line=True)

    def _eval_batch(self, trainer: pl.Trainer) -> None:
        if self._active(trainer) and self._eval is not None:
            self._eval.update(1)

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self._eval_batch(trainer)

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self._eval_batch(trainer)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._active(trainer):
            scores = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}
            print(f"validation at step {trainer.global_step}: {_format(scores)}", flush=True)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._active(trainer) and self._train is not None:
            self._train.close()


def progress_callback(mode: str) -> ProgressBar | None:
    """The Lightning progress display for a `progress=` mode (None for none)."""
    mode = resolve_mode(mode)
    return {"rich": StepRichProgressBar, "tqdm": TQDMProgressBar, "plain": LineProgressBar}.get(mode, lambda: None)()
