"""LightningDataModule over the on-the-fly synthetic DRRs of :mod:`data_synth`."""

from __future__ import annotations

from pathlib import Path

import lightning as L
from torch.utils.data import DataLoader


def synth_config(source: str | dict | None):
    """A ``data_synth.SynthConfig`` from a YAML path, a dict of fields, or None (defaults)."""
    from data_synth import SynthConfig

    if source is None:
        return SynthConfig()
    if isinstance(source, dict):
        return SynthConfig.from_dict(source)
    if not Path(source).exists():
        raise FileNotFoundError(f"synthesis config not found: {source}")
    return SynthConfig.from_yaml(source)


class CupDataModule(L.LightningDataModule):
    """Training and validation streams of synthetic images, deterministic per seed.

    Args:
        synth: synthesis config for training (YAML path or dict of ``SynthConfig`` fields).
        val_synth: synthesis config for validation (default: ``synth``).
        batch_size: images per batch (default collate; the config fixes the image size).
        num_workers: DataLoader workers (the dataset splits its stream between them).
        train_seed, val_seed: dataset seeds (distinct, so validation images are unseen).
        train_length: images per training epoch (None: endless, bounded by ``max_steps``).
        val_length: validation images.
    """

    def __init__(
        self,
        synth: str | dict | None = None,
        val_synth: str | dict | None = None,
        batch_size: int = 8,
        num_workers: int = 0,
        train_seed: int = 0,
        val_seed: int = 1_000_003,
        train_length: int | None = None,
        val_length: int = 32,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()

    def _dataset(self, source: str | dict | None, seed: int, length: int | None):
        from data_synth import SynthDataset

        return SynthDataset(synth_config(source), seed=seed, length=length)

    def train_dataloader(self) -> DataLoader:
        hp = self.hparams
        return DataLoader(self._dataset(hp.synth, hp.train_seed, hp.train_length),
                          batch_size=hp.batch_size, num_workers=hp.num_workers,
                          persistent_workers=hp.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        hp = self.hparams
        source = hp.val_synth if hp.val_synth is not None else hp.synth
        return DataLoader(self._dataset(source, hp.val_seed, hp.val_length),
                          batch_size=hp.batch_size, num_workers=0)
