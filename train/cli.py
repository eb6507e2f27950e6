"""``cupnet train`` / ``python -m train``: LightningCLI over CupNetModule and CupDataModule.

``cupnet train --config configs/cpu.yaml`` runs ``fit``; LightningCLI's ``fit`` and ``validate``
work too (``cupnet train fit -c configs/cpu.yaml --ckpt_path
runs/cpu/checkpoints/last.ckpt`` resumes: the checkpoint's file, not Lightning's ``last``).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import Any

import yaml
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.utilities import rank_zero_warn

SUBCOMMANDS = ("fit", "validate")
# LightningCLI's others, which the module has no step for: what does their job instead.
NOT_OFFERED = {"test": "cupnet evaluate (on cupnet synth's images)",
               "predict": "cupnet predict"}


def flat_settings(settings: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts (and jsonargparse Namespaces) -> ``{"model.rim_channels": 8, ...}``."""
    if hasattr(settings, "as_dict"):
        settings = settings.as_dict()
    if not isinstance(settings, dict):
        return {prefix: settings}
    out: dict[str, Any] = {}
    for key, value in settings.items():
        out.update(flat_settings(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def same_setting(given: Any, kept: Any) -> bool:
    """Whether a setting as given (a command line's text, or a config file's value) is the
    value a checkpoint kept: ``'96'`` is 96, ``'1e-3'`` is 0.001, ``'false'`` is False."""
    if given == kept:
        return True
    if not isinstance(given, str) or isinstance(kept, str) or kept is None:
        return False
    try:
        read = yaml.safe_load(given)
        return read == kept or (not isinstance(kept, bool) and type(kept)(given) == kept)
    except (yaml.YAMLError, TypeError, ValueError):
        return False


class CupNetCLI(LightningCLI):
    """LightningCLI offering ``fit`` and ``validate``, whose resumes take a checkpoint file
    and say which model settings they drop.

    With ``--ckpt_path`` Lightning takes the module's settings from the checkpoint, over any
    ``--model.*`` value or config file given; it did so silently, so a changed learning
    rate or network setting looked taken and was not. It does so for a file only: with a
    keyword (``last``, ``best``) the given settings were built into the module and recorded,
    while the checkpoint's optimiser and schedule were restored beside them. One setting is
    the command's, where it gives one: ``export_path``, where the model is written, as the
    run's folders and loggers are (the checkpoint's had written over the first run's
    export)."""

    def instantiate_classes(self) -> None:
        """The module, data module and trainer; a setting they refuse (a misspelt network
        setting, a missing synthesis config, weights that do not fit) is an argument error
        naming it, as a setting of the wrong type is, where it had ended in a traceback."""
        try:
            super().instantiate_classes()
        except (ValueError, FileNotFoundError) as exc:
            self.parser.error(str(exc))

    @staticmethod
    def subcommands() -> dict[str, set[str]]:
        return {name: skipped for name, skipped in LightningCLI.subcommands().items()
                if name in SUBCOMMANDS}

    def _parse_ckpt_path(self) -> None:
        command = self.config.get("subcommand")
        checkpoint = self.config[command].get("ckpt_path") if command else None
        if checkpoint is not None and not Path(checkpoint).is_file():
            self.parser.error(f"--ckpt_path {checkpoint}: no such checkpoint file; give the "
                              "file itself, such as runs/<config>/checkpoints/last.ckpt (a "
                              "resume takes its model settings from it)")
        problem = None if checkpoint is None else training_checkpoint_problem(Path(checkpoint))
        if problem is not None:
            self.parser.error(f"--ckpt_path {checkpoint}: {problem}")
        given = flat_settings(self.config[command].get("model")) if command else {}
        super()._parse_ckpt_path()
        if not given:
            return
        # Where the export goes is this command's, where it names one, as its folders and
        # loggers are: the checkpoint's had written a resume into a new folder over the
        # first run's export. Where it names none, the checkpoint's still serves.
        if given.get("export_path") is not None:
            self.config[command]["model"]["export_path"] = given["export_path"]
        kept = flat_settings(self.config[command].get("model"))
        dropped = [f"--model.{key} {given[key]!r} (the checkpoint's: {kept.get(key)!r})"
                   for key in given if not same_setting(given[key], kept.get(key))]
        if dropped:
            rank_zero_warn("resuming from a checkpoint takes its model settings, so these "
                           "given ones are not used: " + "; ".join(dropped) + ". To change "
                           "them, start a new stage from the run's export "
                           "(--model.init_weights) instead of resuming")


def training_checkpoint_problem(path: Path) -> str | None:
    """Why ``path`` cannot be resumed from (None where it can): a file torch cannot read, or
    one that is no Lightning checkpoint (a model's exported weights, which start a run with
    ``--model.init_weights``). Lightning had failed in a traceback, some without the file's
    name."""
    import torch

    from cupnet.errors import whole_reason

    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch fails in many ways on a bad file
        return (f"not a readable checkpoint (corrupt, cut short or another format: "
                f"{whole_reason(exc, 200)}); to start from a model's weights give "
                "--model.init_weights")
    if not isinstance(checkpoint, dict) or "pytorch-lightning_version" not in checkpoint:
        return ("not a checkpoint of cupnet train (a model's weights?); to start from them "
                "give --model.init_weights")
    return None


def lightning_args(argv: list[str]) -> list[str]:
    """Arguments for LightningCLI: ``fit`` is implied when no sub-command is given.

    Raises:
        ValueError: ``test`` or ``predict``, which CupNetModule has no step for (Lightning
            failed with "No test_step()"), naming the command to use.
    """
    if argv and argv[0] in NOT_OFFERED:
        raise ValueError(f"cupnet train {argv[0]} is not offered; use "
                         f"{NOT_OFFERED[argv[0]]}")
    if argv and (argv[0] in SUBCOMMANDS or argv[0] in ("-h", "--help")):
        return list(argv)
    return ["fit", *argv]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("argv", nargs=argparse.REMAINDER,
                        help="LightningCLI arguments, e.g. --config configs/cpu.yaml "
                             "(or: fit -c configs/cpu.yaml --ckpt_path <checkpoint>)")
    # Every argument, options and -h included, belongs to LightningCLI: argparse would
    # otherwise reject a leading option such as --config before filling the REMAINDER.
    parser.prefix_chars = "\0"


def main(argv: list[str]) -> int:
    """LightningCLI on ``argv``; 2 for a sub-command not offered (said on stderr)."""
    from train.data import CupDataModule
    from train.module import CupNetModule

    try:
        args = lightning_args(argv)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 2
    with warnings.catch_warnings():
        # cupnet train hands LightningCLI its own arguments, not sys.argv's, by design.
        warnings.filterwarnings("ignore", "LightningCLI's args parameter is intended")
        CupNetCLI(CupNetModule, CupDataModule, args=args, parser_kwargs={"prog": "cupnet train"},
                  save_config_kwargs={"overwrite": True})
    return 0


def run(args: argparse.Namespace) -> int:
    return main(args.argv)
