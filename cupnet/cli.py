"""The ``cupnet`` command: one sub-command per job, each implemented in its own module.

Every sub-command module exposes ``add_arguments(parser)`` and ``run(args) -> int``; they are
imported lazily so ``cupnet --help`` stays fast and a sub-command's heavy imports load only
when it runs.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings
from typing import NoReturn

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "solve": ("cupnet.solve_cli", "solve cup poses from landmark files (no network)"),
    "synth": ("data_synth.cli", "synthesise fluoroscopy images of hip cups with ground truth"),
    "train": ("train.cli", "train CupNet from a YAML config (LightningCLI)"),
    "predict": ("cupnet.predict", "cup poses from images or DICOMs: CSV, JSON and overlays"),
    "evaluate": ("cupnet.evaluate", "compare results.csv with truth.csv: tables, plots, report"),
    "demo": ("cupnet.demo", "synthesise, predict and evaluate a small set end to end"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cupnet", description=__doc__.splitlines()[0])
    from cupnet import __version__

    parser.add_argument("--version", action="version", version=f"cupnet {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (_, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    if not argv or argv[0] not in COMMANDS:
        parser.parse_args(argv)  # prints help / the error and exits
        return 2
    # A dependency scripts a function with torch.jit at import: not the user's concern.
    warnings.filterwarnings("ignore", category=FutureWarning, message=".*torch.jit.script.*")
    name, rest = argv[0], argv[1:]
    module = importlib.import_module(COMMANDS[name][0])
    sub_parser = argparse.ArgumentParser(prog=f"cupnet {name}", description=COMMANDS[name][1])
    module.add_arguments(sub_parser)
    args = sub_parser.parse_args(rest)
    return int(module.run(args) or 0)


def console() -> NoReturn:
    """The installed ``cupnet`` command: :func:`main`, then exit with its status.

    A run stopped by a signal or Ctrl-C returns 128 + the signal's number once it has
    written what finished. Its detection threads are still on the batches in flight, and
    the interpreter would wait for them at exit (5 s measured for the default's two batches
    of 8 at 512 px; past ``docker stop``'s 10 s grace for larger ones), so such a run
    exits at once, its printed lines flushed first.
    """
    status = main()
    if status > 128:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":
    console()
