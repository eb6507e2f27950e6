"""``cupnet train`` / ``python -m train``: LightningCLI over CupNetModule and CupDataModule.

``cupnet train --config configs/cpu.yaml`` runs ``fit``; LightningCLI's own sub-commands work
too (``cupnet train fit -c configs/cpu.yaml --ckpt_path last.ckpt`` resumes).
"""

from __future__ import annotations

import argparse

from lightning.pytorch.cli import LightningCLI

SUBCOMMANDS = ("fit", "validate", "test", "predict")


def lightning_args(argv: list[str]) -> list[str]:
    """Arguments for LightningCLI: ``fit`` is implied when no sub-command is given."""
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


def main(argv: list[str]) -> None:
    from train.data import CupDataModule
    from train.module import CupNetModule

    LightningCLI(CupNetModule, CupDataModule, args=lightning_args(argv),
                 save_config_kwargs={"overwrite": True})


def run(args: argparse.Namespace) -> int:
    main(args.argv)
    return 0
