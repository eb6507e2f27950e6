"""``cupnet demo``: synthesise a small set, predict with the shipped model, evaluate it.

The whole job on a fresh machine in one command: ``cupnet synth`` writes about two dozen
fluoroscopy images with CT anatomy and exact ground truth, ``cupnet predict`` estimates the
cup poses with the shipped checkpoint, and ``cupnet evaluate`` prints the paper's table and
writes the plots and report. Each step is the ordinary sub-command, so the demo shows the
commands a user runs on their own images.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
import time
from pathlib import Path

STEPS = ("data", "predict", "evaluate")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path,
                        help="folder for data/, predict/ and evaluate/ (default: a new "
                             "temporary folder)")
    parser.add_argument("--n", type=int, default=24, help="number of synthetic images")
    parser.add_argument("--seed", type=int, default=0, help="synthesis seed")
    parser.add_argument("--size", type=int, default=512,
                        help="square image side in pixels (default 512: the model trains and "
                        "is benchmarked on 512-1024 px images)")
    parser.add_argument("--checkpoint", type=Path, help="model weights (default: shipped)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the outputs of an earlier demo in --out")


def commands(out: Path, n: int, seed: int, checkpoint: Path | None,
             overwrite: bool, size: int = 512) -> list[list[str]]:
    """The three ``cupnet`` command lines the demo runs (without the leading ``cupnet``)."""
    data, pred, evaluation = (out / step for step in STEPS)
    again = ["--overwrite"] if overwrite else []
    predict = ["predict", str(data / "images"), "--out", str(pred), "--meta",
               str(data / "meta.csv"), *again]
    if checkpoint is not None:
        predict += ["--checkpoint", str(checkpoint)]
    return [
        ["synth", "--n", str(n), "--seed", str(seed), "--size", str(size), str(size),
         "--out", str(data), *again],
        predict,
        ["evaluate", "--pred", str(pred / "results.csv"), "--truth", str(data / "truth.csv"),
         "--out", str(evaluation)],
    ]


def run(args: argparse.Namespace) -> int:
    from cupnet.cli import main

    if args.n < 1:
        print("cupnet demo: error: --n must be >= 1", file=sys.stderr)
        return 2
    out = args.out if args.out is not None else Path(tempfile.mkdtemp(prefix="cupnet-demo-"))
    start = time.perf_counter()
    for argv in commands(out, args.n, args.seed, args.checkpoint, args.overwrite, args.size):
        print(f"\n$ cupnet {shlex.join(argv)}", file=sys.stderr, flush=True)
        code = main(argv)
        if code != 0:
            print(f"cupnet demo: step 'cupnet {argv[0]}' failed (exit {code})", file=sys.stderr)
            return code
    print(f"\ndemo finished in {time.perf_counter() - start:.0f} s\n"
          f"  overlays: {out / 'predict' / 'overlays'}\n"
          f"  results:  {out / 'predict' / 'results.csv'}\n"
          f"  review:   {out / 'predict' / 'review.html'} (each pose beside its overlay)\n"
          f"  plots:    {out / 'evaluate' / 'plots'}\n"
          f"  report:   {out / 'evaluate' / 'report.md'}")
    return 0
