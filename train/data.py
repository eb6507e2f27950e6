"""LightningDataModule over the on-the-fly synthetic DRRs of :mod:`data_synth`.

A synthesis config fixes one image size, and a batch needs one size, so the training stream
takes whole batches from one dataset per image size in turn (round robin): the network sees
every size, each batch collates with the default collate.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import lightning as L
import torch
from torch.utils.data import DataLoader, IterableDataset, default_collate, get_worker_info

if TYPE_CHECKING:  # data_synth loads where a config is made
    from data_synth import SynthConfig


def synth_config(source: str | dict | None,
                 image_size: int | tuple[int, int] | list[int] | None = None
                 ) -> SynthConfig:
    """A ``data_synth.SynthConfig`` from a YAML path, a dict of fields, or None (defaults),
    with ``image_size`` when given: a square side, or ``(width, height)`` pixels."""
    from data_synth import SynthConfig

    if source is None:
        config = SynthConfig()
    elif isinstance(source, dict):
        config = SynthConfig.from_dict(source)
    elif not Path(source).exists():
        raise FileNotFoundError(f"synthesis config not found: {source}")
    else:
        config = SynthConfig.from_yaml(source)
    if isinstance(image_size, int):
        config = dataclasses.replace(config, image_size=(image_size, image_size))
    elif image_size is not None:
        config = dataclasses.replace(config, image_size=tuple(image_size))
    return config


def images_in(batch: dict) -> int:
    """Images in a collated batch (``ThroughputMonitor``'s ``batch_size_fn`` in a config)."""
    return batch["image"].shape[0]


class RoundRobinBatches(IterableDataset):
    """Collated batches taken in turn from several sample streams (one per image size).

    Args:
        datasets: ``data_synth.SynthDataset`` s (or iterable datasets of sample dicts with
            a ``samples(skip, rotate)`` method).
        batch_size: samples per batch.
        batches: batches the loader makes, its workers together (an epoch of
            ``train_batches``; None: until a stream ends).
        done: batches already trained on (a resumed run): each stream starts after its
            share of them, so the run goes on with the batches it would have made without
            the stop, in their order. A DataLoader takes its workers' batches in turn, so
            of the first ``done`` the worker ``w`` of ``W`` made those numbered ``w, w + W,
            ...``; resumed, worker 0 comes first again, so it plays worker ``done % W``.
    """

    def __init__(self, datasets: list, batch_size: int, batches: int | None = None,
                 done: int = 0) -> None:
        self.datasets, self.batch_size, self.batches = datasets, batch_size, batches
        self.done = done
        # Epochs this copy began: the main process's, or a persistent worker's, which keeps
        # it from epoch to epoch (so each epoch goes on with the streams).
        self.epochs = 0

    def __iter__(self) -> Iterator[dict]:
        info = get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        done = self.done + self.epochs * (self.batches or 0)  # the loader's, all workers'
        self.epochs += 1
        role = (worker + done) % workers
        count = len(range(role, done, workers))  # batches its role made before
        n = len(self.datasets)
        streams = [d.samples(len(range(j, count, n)) * self.batch_size, rotate=done)
                   for j, d in enumerate(self.datasets)]
        # This worker's part of the loader's `batches` (the workers take turns).
        mine = None if self.batches is None else len(range(worker, self.batches, workers))
        made = 0
        while mine is None or made < mine:
            stream = streams[count % len(streams)]
            samples = [s for _, s in zip(range(self.batch_size), stream, strict=False)]
            if len(samples) < self.batch_size:
                return
            yield default_collate(samples)
            count, made = count + 1, made + 1


class CupDataModule(L.LightningDataModule):
    """Training and validation streams of synthetic images, deterministic per seed.

    Args:
        synth: synthesis config (YAML path or dict of ``SynthConfig`` fields), or a list of
            them, mixed batch by batch (e.g. a stream of hard cases beside the usual one).
        image_sizes: training image sizes, taken in turn batch by batch: square sides (px)
            or ``[width, height]`` (oblong images; see ``train.module.CupNetModule``'s
            locator stage); None keeps the config's ``image_size``.
        val_synth: synthesis config for validation (default: ``synth``, its first).
        val_image_size: validation image size (None: the config's).
        batch_size: images per batch.
        num_workers: DataLoader workers of the training stream (the synthetic dataset gives
            each worker its own share of the stream).
        train_seed, val_seed: dataset seeds (distinct, so validation images are unseen); the
            ``i``-th stream (configs in order, sizes within each) uses ``train_seed + i``.
        train_batches: batches per training epoch (None: endless, bounded by ``max_steps``).
        val_length: validation images.
    """

    def __init__(
        self,
        synth: str | dict | list | None = None,
        image_sizes: list[int | list[int]] | None = None,
        val_synth: str | dict | None = None,
        val_image_size: int | None = None,
        batch_size: int = 8,
        num_workers: int = 0,
        train_seed: int = 0,
        val_seed: int = 1_000_003,
        train_batches: int | None = None,
        val_length: int = 32,
    ) -> None:
        super().__init__()
        for name, value, least in (("batch_size", batch_size, 1), ("num_workers", num_workers, 0),
                                   ("train_batches", train_batches, 1),
                                   ("val_length", val_length, 1)):
            if value is not None and value < least:
                raise ValueError(f"{name} must be >= {least}, got {value}")
        self.save_hyperparameters()
        # Read now, so that a missing or bad synthesis config stops the run before the
        # model, loggers and trainer are made (it had failed at the first batch): the
        # training streams' configs (configs in order, sizes within each) and validation's.
        self.train_configs = [synth_config(source, size) for source in self._synth_list()
                              for size in image_sizes or [None]]
        self.val_config = synth_config(val_synth if val_synth is not None
                                       else self._synth_list()[0], val_image_size)

    def _synth_list(self) -> list:
        synth = self.hparams.synth
        return list(synth) if isinstance(synth, list | tuple) else [synth]

    def train_dataset(self) -> RoundRobinBatches:
        from data_synth import SynthDataset

        hp = self.hparams
        datasets = [SynthDataset(config, seed=hp.train_seed + i)
                    for i, config in enumerate(self.train_configs)]
        # A run resumed from a checkpoint has its step back by now: it goes on with new
        # images rather than the first ones again.
        done = self.trainer.global_step if self.trainer is not None else 0
        return RoundRobinBatches(datasets, hp.batch_size, hp.train_batches, done)

    def train_dataloader(self) -> DataLoader:
        hp = self.hparams
        return DataLoader(self.train_dataset(), batch_size=None, num_workers=hp.num_workers,
                          persistent_workers=hp.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        from data_synth import SynthDataset

        hp = self.hparams
        dataset = SynthDataset(self.val_config, seed=hp.val_seed, length=hp.val_length)
        # A generator of its own: each validation's iterator draws its base seed from it,
        # not from torch's global one, whose draws the training steps make (from the
        # checkpoint's state on a resume, taken before the validation that follows it).
        return DataLoader(dataset, batch_size=hp.batch_size, num_workers=0,
                          generator=torch.Generator().manual_seed(hp.val_seed))
