"""Where the batched pipelines' time goes on one device, stage by stage.

Rerun: ``.venv/bin/python -m benchmarks.stages [--device cuda] [--batch 1024] [--images 128]``
(``benchmarks/gpu_check.sh`` runs it on a lent GPU). Writes the ``stages_<device type>``
section of docs/benchmarks.md.

Each pipeline of :data:`benchmarks.throughput.BATCHED` runs on ``--batch`` 512 x 512 DRRs
(``--images`` distinct ones, repeated) once to warm up, then once with each of
:data:`STAGES` wrapped in a timer that synchronises the device before and after it. A row
is a stage's wall time, the stages it calls included (so the rows overlap and do not sum to
the total), over all its calls in the pipeline; the timers' own syncs add a little to the
total.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from collections.abc import Callable
from contextlib import ExitStack
from unittest import mock

import torch

import cupnet.batched
import cupnet.model
from benchmarks.model import samples
from benchmarks.report import machine, markdown_table, write_section
from benchmarks.throughput import BATCHED, stacked, synchronise
from cupnet.fold import fold_batchnorm
from cupnet.model import CupNet, load_model
from cupnet.offload import resolve_device

# CupNet's stages timed: its methods, and (module, function) pairs for the CPU work that
# runs outside them (each image's round field and locator blobs, the display's judgement).
STAGES: tuple[str | tuple[object, str], ...] = (
    "locate", "locate_windows", "rough_ellipses", "ellipses_from_locator", "segment_crops",
    "crop_landmarks", "refiner_fit", "trusted_rim_landmarks", "rim_landmarks",
    "coarse_framed_rim_landmarks", "ranked_thin_rim_landmarks", "solve", "outline_refined",
    "pose_doubt",
    (cupnet.model, "map_on_cores"), (cupnet.batched, "metals_show_bright"))
# What a row's stage does, where its name does not say it.
NOTES = {"map_on_cores": " (each image's round field and locator blobs, on the CPU)"}


def stage_seconds(pipeline: Callable[..., object], model: CupNet, inputs: tuple,
                  device: torch.device) -> tuple[float, dict[str, tuple[int, float]]]:
    """Wall seconds of one call of ``pipeline`` on ``inputs`` (images, geometry, diameters)
    after a warm-up call, and per stage of :data:`STAGES` that ran, ``(calls, seconds)``."""
    with torch.inference_mode():
        pipeline(model, *inputs)
    spent: dict[str, list] = defaultdict(lambda: [0, 0.0])

    def timed(name: str, function: Callable) -> Callable:
        def wrapper(*args: object, **kwargs: object) -> object:
            synchronise(device)
            start = time.perf_counter()
            out = function(*args, **kwargs)
            synchronise(device)
            spent[name][0] += 1
            spent[name][1] += time.perf_counter() - start
            return out
        return wrapper

    with ExitStack() as patches, torch.inference_mode():
        for stage in STAGES:
            owner, name = (model, stage) if isinstance(stage, str) else stage
            patches.enter_context(mock.patch.object(owner, name,
                                                    timed(name, getattr(owner, name))))
        synchronise(device)
        start = time.perf_counter()
        pipeline(model, *inputs)
        synchronise(device)
        total = time.perf_counter() - start
    return total, {name: (calls, seconds) for name, (calls, seconds) in spent.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batch", type=int, help="images a call (default: 1024 on a GPU, 16 "
                                                  "on a CPU)")
    parser.add_argument("--images", type=int, default=128, help="distinct DRRs")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--seed", type=int, default=20_261_124)
    args = parser.parse_args()
    device = resolve_device(args.device)
    torch.set_num_threads(args.threads)
    batch = args.batch or (1024 if device.type != "cpu" else 16)
    data = samples("configs/synth_speed.yaml", args.seed, min(args.images, batch))
    inputs = stacked((data * -(-batch // len(data)))[:batch], device)
    model = fold_batchnorm(load_model()).to(device)
    rows = []
    for label, pipeline in BATCHED.items():
        total, stages = stage_seconds(pipeline, model, inputs, device)
        rows.append([label, "whole call", 1, f"{1000 * total:.1f}", "100 %"])
        rows += [[label, f"`{name}`{NOTES.get(name, '')}", calls, f"{1000 * seconds:.1f}",
                  f"{100 * seconds / total:.0f} %"]
                 for name, (calls, seconds) in sorted(stages.items(), key=lambda s: -s[1][1])]
        print(f"{label}: {batch / total:.0f} images/s with the timers", flush=True)
    table = markdown_table(["pipeline", "stage", "calls", "ms", "of the call"], rows)
    print(table)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else device.type
    command = (f"python -m benchmarks.stages --device {args.device} --batch {batch} "
               f"--images {len(data)} --threads {args.threads}")
    write_section(f"stages_{device.type}", (
        f"## CupNet's batched pipelines stage by stage on {name}\n\n`{command}` on "
        f"{machine()}. One call of {batch} 512 x 512 DRRs with the CT background after a "
        "warm-up call; each stage's wall time over its calls, the stages it calls included "
        "(rows overlap), the device synchronised around each (see "
        "`benchmarks/stages.py`).\n\n" + table))


if __name__ == "__main__":
    main()
