"""The ``cupnet`` command: one sub-command per job, each implemented in its own module.

Every sub-command module exposes ``add_arguments(parser)`` and ``run(args) -> int``; they are
imported lazily so ``cupnet --help`` stays fast and a sub-command's heavy imports load only
when it runs.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

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


if __name__ == "__main__":
    raise SystemExit(main())
