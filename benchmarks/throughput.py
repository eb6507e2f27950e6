"""Images per second of CupNet on one device: batched end to end, and ``detect`` as predict runs it.

Rerun: ``.venv/bin/python -m benchmarks.throughput [--device cuda] [--batches 1 64 256]
[--images 256] [--precision fp32 bf16]``; on a lent GPU the defaults measure it (``--device``
defaults to cuda where there is one; ``benchmarks/gpu_check.sh`` runs it there, with the
wheels that machine lacks). Writes the ``throughput_<device type>`` section of
docs/benchmarks.md.

Four pipelines, on 512 x 512 DRRs with the CT background (``configs/synth_speed.yaml``):

- **batched**, the whole model and the images on the device, ``B`` images a call, every
  stage on all cups at once (the locator's connected components with OpenCV, on the CPU):
  - ``CupNet.forward``, the path training backpropagates through, with the solver's
    maximum-likelihood refinement: locator, one refiner pass, the fine rim stage's
    passes, the pose solver;
  - :func:`cupnet.batched.batched_cups`: ``detect``'s landmark sources (the locator's
    retry and score, two refiner passes, the thin-rim hypotheses, the coarse stage and
    the refiner for the cups with no pose in range), and again with ``outline=True``,
    ``detect``'s dome-outline stage too.
  None has ``detect``'s verification, search or later looks, so all are less accurate:
  their pose MAE and share of cups found are measured on the same images and given beside
  them.
- **detect** (``CupNet.detect``, the shipped model's accuracy; with each speed preset):
  the networks on the device, the geometry between their calls on the CPU
  (:func:`cupnet.offload.networks_on`, as ``cupnet predict --device`` runs it), 8 images
  a call.

Each figure is the best of ``--repeats`` timed passes over the images after a warm-up pass
(the device synchronised before each clock reading).
"""

from __future__ import annotations

import argparse
import copy
import time
from collections.abc import Callable
from contextlib import nullcontext
from functools import partial
from types import SimpleNamespace

import numpy as np
import torch

from benchmarks.model import samples
from benchmarks.report import machine, markdown_row, markdown_table, write_section
from cupnet.batched import BatchedCups, batched_cups
from cupnet.config import SPEED_PRESETS, apply_speed_preset
from cupnet.fold import fold_batchnorm
from cupnet.geometry import Geometry
from cupnet.model import CupNet, load_model
from cupnet.offload import networks_on, resolve_device
from cupnet.runtime import RUNTIMES, networks_in_onnx_runtime
from train.losses import POSE_NAMES
from train.module import score_detections

DETECT_BATCH = 8  # images per detect call, as cupnet predict's default --batch-size


def synchronise(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def best_seconds(run: Callable[[], object], device: torch.device, repeats: int) -> float:
    """Wall seconds of the fastest of ``repeats`` calls of ``run`` after one warm-up call."""
    run()
    times = []
    for _ in range(repeats):
        synchronise(device)
        start = time.perf_counter()
        run()
        synchronise(device)
        times.append(time.perf_counter() - start)
    return min(times)


def stacked(data: list[dict], device: torch.device) -> tuple[torch.Tensor, Geometry, torch.Tensor]:
    """Images ``(B, 1, H, W)``, geometry and cup diameters ``(B,)`` mm on ``device``."""
    images = torch.stack([s["image"] for s in data]).to(device)
    rows = torch.stack([s["geometry"] for s in data]).double().to(device)
    diameter = torch.stack([s["cup_diameter"][0] for s in data]).double().to(device)
    return images, Geometry.from_rows(rows), diameter


def forward_cups(model: CupNet, images: torch.Tensor, geometry: Geometry,
                 diameter: torch.Tensor) -> BatchedCups:
    """The training path's cups: ``CupNet.forward`` with its solver's ML refinement."""
    out = model(images, geometry, diameter, refine_pose=True)
    return BatchedCups(out.cup_index, out.solution.pose, out.solution.ellipse,
                       out.solution.valid, out.solution.alt_pose)


# The batched pipelines: name in the table -> images, geometry, diameters -> cups.
BATCHED = {"batched (`CupNet.forward`)": forward_cups,
           "batched (`batched_cups`)": batched_cups,
           "batched (`batched_cups`, outline)": partial(batched_cups, outline=True)}


def batched_detections(pipeline: Callable[..., BatchedCups], model: CupNet, data: list[dict],
                       device: torch.device, batch: int, precision: torch.dtype | None
                       ) -> list[list[SimpleNamespace]]:
    """Per image, a batched ``pipeline``'s cups (``pose``, ``ellipse`` as numpy arrays)."""
    found: list[list[SimpleNamespace]] = []
    for first in range(0, len(data), batch):
        images, geometry, diameter = stacked(data[first:first + batch], device)
        with autocast(device, precision):
            cups = pipeline(model, images, geometry, diameter)
        poses, ellipses = cups.pose.cpu().numpy(), cups.ellipse.cpu().numpy()
        owner = cups.cup_index[:, 0].cpu().numpy()
        found += [[SimpleNamespace(pose=poses[k], ellipse=ellipses[k])
                   for k in np.flatnonzero(owner == b)] for b in range(len(images))]
    return found


def autocast(device: torch.device, precision: torch.dtype | None) -> object:
    """Autocast of the networks' float32 work to ``precision`` (None: as they are); the
    solver's float64 is left alone."""
    return (torch.autocast(device.type, dtype=precision) if precision is not None
            else nullcontext())


def scores(found: list[list], data: list[dict]) -> dict[str, float]:
    """Pose MAE of the matched cups and the share of true cups found with a pose."""
    errors, detected, total = [], 0, 0
    for cups, s in zip(found, data, strict=True):
        e, d, t, _ = score_detections(cups, s["pose"].double().numpy(), s["ellipse"].numpy(),
                                      s["cup_valid"].numpy().astype(bool))
        errors, detected, total = errors + e, detected + d, total + t
    mae = np.mean(errors, 0) if errors else np.full(5, np.nan)
    return {**dict(zip(POSE_NAMES, mae.tolist(), strict=True)), "found": detected / max(total, 1)}


def table_row(pipeline: str, networks: str, per_call: int, images: int, seconds: float,
              quality: dict[str, float]) -> list[object]:
    """One row of the table: the pipeline, its speed over ``images`` in ``seconds``, and
    its :func:`scores`. Printed at once too, so that a run stopped at its time limit (as on
    a lent GPU machine) still shows the rows it measured."""
    row = [pipeline, networks, per_call, f"{images / seconds:.1f}",
           f"{1000 * seconds / images:.2f}", *(f"{quality[n]:.2f}" for n in POSE_NAMES),
           f"{100 * quality['found']:.1f} %"]
    print(markdown_row(row), flush=True)
    return row


def batched_rows(model: CupNet, data: list[dict], device: torch.device, batches: list[int],
                 precisions: list[str], repeats: int) -> list[list[object]]:
    model = fold_batchnorm(model).to(device)
    rows = []
    for label, pipeline in BATCHED.items():
        for name in precisions:
            precision = None if name == "fp32" else getattr(torch, {"bf16": "bfloat16",
                                                                   "fp16": "float16"}[name])
            with torch.inference_mode():
                found = batched_detections(pipeline, model, data, device, max(batches),
                                           precision)
            quality = scores(found, data)
            for batch in batches:
                # At least one full call, and 32 images for the small batches (not all of
                # them: one image a call is slow, and its figure steady after a few dozen).
                count = max(batch, min(len(data), 32))
                part = (data * -(-count // len(data)))[:count]
                groups = [stacked(part[i:i + batch], device)
                          for i in range(0, len(part), batch)]

                def run(groups: list = groups, precision: torch.dtype | None = precision,
                        pipeline: Callable[..., BatchedCups] = pipeline) -> None:
                    with torch.inference_mode(), autocast(device, precision):
                        for images, geometry, diameter in groups:
                            pipeline(model, images, geometry, diameter)

                seconds = best_seconds(run, device, repeats)
                count = sum(len(g[0]) for g in groups)
                rows.append(table_row(label, name, batch, count, seconds, quality))
    return rows


def detect_rows(model: CupNet, data: list[dict], device: torch.device, repeats: int,
                runtime: str = "torch") -> list[list[object]]:
    """Rows of ``detect`` with each speed preset, its networks on ``device`` (``runtime``
    ``"onnx"``: run by ONNX Runtime on the CPU, :mod:`cupnet.runtime`)."""
    folded = fold_batchnorm(model)
    moved = (networks_in_onnx_runtime(folded) if runtime == "onnx"
             else networks_on(folded, device))
    networks = "fp32, ONNX Runtime" if runtime == "onnx" else "fp32"
    shipped = moved.config
    rows = []
    for preset in [None, *SPEED_PRESETS]:
        moved.config = apply_speed_preset(copy.copy(shipped), preset)
        found: list[list] = []

        def run(found: list = found) -> None:
            found.clear()
            for first in range(0, len(data), DETECT_BATCH):
                images, geometry, diameter = stacked(data[first:first + DETECT_BATCH],
                                                     torch.device("cpu"))
                found += moved.detect(images, geometry, diameter, return_masks=False)

        seconds = best_seconds(run, device, repeats)
        quality = scores(found, data)
        rows.append(table_row(f"`detect`{f', --{preset}' if preset else ''}", networks,
                              DETECT_BATCH, len(data), seconds, quality))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batches", type=int, nargs="+")
    parser.add_argument("--images", type=int,
                        help="distinct DRRs (default: 256 on a GPU, 32 on a CPU)")
    parser.add_argument("--precision", nargs="+", default=["fp32"],
                        choices=["fp32", "bf16", "fp16"],
                        help="the networks' precision in the batched pipeline")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--detect-images", type=int, default=32,
                        help="images of the detect rows (0: skip them)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--runtimes", nargs="+", default=["torch"], choices=RUNTIMES,
                        help="what runs detect's networks (onnx: ONNX Runtime, CPU only)")
    parser.add_argument("--seed", type=int, default=20_261_124)
    args = parser.parse_args()
    device = resolve_device(args.device)
    if device.type == "mps":  # the batched pipeline's solver is float64 on the device
        parser.error("--device mps: MPS has no float64; cupnet predict --device mps runs the "
                     "networks there and solves on the CPU")
    if "onnx" in args.runtimes and device.type != "cpu":
        parser.error("--runtimes onnx: ONNX Runtime runs the networks on the CPU")
    torch.set_num_threads(args.threads)
    gpu = device.type != "cpu"
    batches = args.batches or ([1, 64, 256] if gpu else [1, 16])
    data = samples("configs/synth_speed.yaml", args.seed, args.images or (256 if gpu else 32))
    model = load_model()
    rows = batched_rows(model, data, device, batches, args.precision, args.repeats)
    if args.detect_images:
        for runtime in args.runtimes:
            rows += detect_rows(model, data[:args.detect_images], device, args.repeats,
                                runtime)
    name = (torch.cuda.get_device_name(device) if device.type == "cuda" else device.type)
    table = markdown_table(["pipeline", "networks", "images a call", "images / s",
                            "ms / image", *(f"MAE {n}" for n in POSE_NAMES), "cups found"],
                           rows)
    print(table)
    command = (f"python -m benchmarks.throughput --device {args.device} --batches "
               f"{' '.join(map(str, batches))} --images {len(data)} --precision "
               f"{' '.join(args.precision)} --threads {args.threads} --runtimes "
               f"{' '.join(args.runtimes)}")
    write_section(f"throughput_{device.type}", (
        f"## CupNet throughput on {name}\n\n`{command}` on {machine()}. 512 x 512 DRRs with "
        f"the CT background ({len(data)} distinct images; each batch size timed on at least "
        "one full call and 32 images, repeated where there are fewer); the batched pipelines "
        "are `CupNet.forward` (the training path: one refiner pass, the fine rim stage, the "
        "solver with its ML refinement) and `cupnet.batched.batched_cups` (detect's "
        "landmark sources: two refiner passes, the thin-rim hypotheses, the coarse stage and "
        "the refiner where they give no pose in range; with `outline` detect's dome-outline "
        "stage too), none with detect's verification, search or later looks; `detect` "
        f"the shipped pipeline with its networks on the device, {DETECT_BATCH} images a "
        "call. MAE in deg (theta, phi) and mm (k, l, h) over the cups each finds: a small "
        "sample, to set the speeds beside what each pipeline gives (the figures of record "
        "are the benchmark's, `CupNet accuracy`). On a lent GPU machine (no package index "
        "there): `make gpu-wheels` here, then `bash benchmarks/gpu_check.sh` there "
        "(see `benchmarks/throughput.py`).\n\n" + table))

if __name__ == "__main__":
    main()
