"""``cupnet train`` / ``python -m train``: LightningCLI over CupNetModule and CupDataModule.

``cupnet train --config configs/cpu.yaml`` runs ``fit``; LightningCLI's ``fit`` and ``validate``
work too (``cupnet train fit -c configs/cpu.yaml --ckpt_path last.ckpt`` resumes).
"""

from __future__ import annotations

import argparse
import sys

from lightning.pytorch.cli import LightningCLI

SUBCOMMANDS = ("fit", "validate")
# LightningCLI's others, which the module has no step for: what does their job instead.
NOT_OFFERED = {"test": "cupnet evaluate (on cupnet synth's images)",
               "predict": "cupnet predict"}


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
    LightningCLI(CupNetModule, CupDataModule, args=args, save_config_kwargs={"overwrite": True})
    return 0


def run(args: argparse.Namespace) -> int:
    return main(args.argv)
