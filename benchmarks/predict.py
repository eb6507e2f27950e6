"""Throughput and peak memory of ``cupnet predict`` on a folder of 16-bit PNGs (1024 px).

Rerun: ``.venv/bin/python -m benchmarks.predict [--images 200] [--checkpoint PATH]
[--runtimes torch onnx] [--size 1024] [--synth-size 256] [--unique 20]``.

The folder is made from ``cupnet synth`` images (CT anatomy, one or two cups or none)
rendered at ``--synth-size`` px and resized to ``--size`` px, with meta.csv scaled to match
(``--synth-size`` equal to ``--size``: DRRs as rendered, as the accuracy benchmarks have
them); a few distinct images are repeated to reach the count (decoding, network and pose
cost depend little on which image it is). A ``--size`` other than 1024 writes its own
section (``predict_<size>``). Each configuration (the default with overlays off, then on, then each
speed preset, ``--fast`` and ``--fastest``, with overlays) runs ``cupnet predict`` in a
fresh process, which first pays its one-off start (imports, model load, first-call set-up of
PyTorch) on one image; the run itself is then timed end to end (reading, network, pose,
writing CSV/JSON and overlays). Peak memory is the process's maximum resident set size. The
CPU time the run used (all threads) is reported too: on a machine whose cores are shared it
is steadier than wall time, and ``cores / (CPU s per image)`` bounds the throughput the run
would reach with the cores to itself.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

from benchmarks.report import machine, markdown_table, write_section
from cupnet.config import SPEED_PRESETS
from cupnet.runtime import RUNTIMES

SIZE = 1024
SYNTH_SIZE = 256
# Runs in the child: start-up on one image, then the timed run, then peak memory.
CHILD = """
import json, resource, sys, time
from cupnet.cli import main
warm, run = json.loads(sys.argv[1])
def cpu():
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime
t0 = time.perf_counter()
assert main(warm) == 0
t1, c1 = time.perf_counter(), cpu()
assert main(run) == 0
t2, c2 = time.perf_counter(), cpu()
print(json.dumps({"startup_s": t1 - t0, "run_s": t2 - t1, "cpu_s": c2 - c1,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def make_folder(root: Path, n_images: int, n_unique: int, seed: int, size: int = SIZE,
                synth_size: int = SYNTH_SIZE) -> tuple[Path, Path]:
    """``root/images`` with ``n_images`` ``size`` px 16-bit PNGs (rendered at ``synth_size``)
    and ``root/meta.csv``."""
    synth = root / "synth"
    subprocess.run([sys.executable, "-m", "cupnet.cli", "synth", "--n", str(n_unique),
                    "--seed", str(seed), "--out", str(synth), "--size", str(synth_size),
                    str(synth_size)], check=True, stdout=subprocess.DEVNULL)
    scale = size / synth_size
    with (synth / "meta.csv").open(newline="") as f:
        meta = list(csv.DictReader(f))
    images = root / "images"
    images.mkdir()
    rows = []
    for i in range(n_images):
        source = meta[i % len(meta)]
        name = f"bench_{i:05d}.png"
        if i < len(meta):
            small = cv2.imread(str(synth / "images" / source["image"]), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(images / name), small if scale == 1 else cv2.resize(
                small, (size, size), interpolation=cv2.INTER_CUBIC))
        else:
            shutil.copyfile(images / f"bench_{i % len(meta):05d}.png", images / name)
        # Same detector, pixels ``scale`` x smaller; pixel centres at integers in both grids.
        rows.append({**source, "image": name,
                     "pixel_spacing_mm": float(source["pixel_spacing_mm"]) / scale,
                     "principal_u_px": (float(source["principal_u_px"]) + 0.5) * scale - 0.5,
                     "principal_v_px": (float(source["principal_v_px"]) + 0.5) * scale - 0.5})
    meta_path = root / "meta.csv"
    with meta_path.open("w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return images, meta_path


def measure(images: Path, meta: Path, out: Path, overlays: bool,
            checkpoint: str | None, preset: str | None = None, runtime: str = "torch") -> dict:
    """One fresh ``cupnet predict`` process (with ``--PRESET`` where given): start-up, timed
    run, peak memory."""
    common = ["--meta", str(meta), "--quiet"] + (["--checkpoint", checkpoint] if checkpoint
                                                 else [])
    common += ([] if overlays else ["--no-overlays"]) + ([f"--{preset}"] if preset else [])
    common += ["--runtime", runtime]
    first = sorted(images.iterdir())[0]
    warm = ["predict", str(first), "--out", str(out / "warm"), *common]
    run = ["predict", str(images), "--out", str(out / "run"), *common]
    result = subprocess.run([sys.executable, "-c", CHILD, json.dumps([warm, run])],
                            check=True, capture_output=True, text=True,
                            env={**os.environ, "PYTHONWARNINGS": "ignore"})
    figures = json.loads(result.stdout.strip().splitlines()[-1])
    with (out / "run" / "results.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    figures["images"] = len({r["image"] for r in rows})
    figures["cups"] = sum(r["status"] in ("ok", "ambiguous") for r in rows)
    figures["errors"] = sum(r["status"].startswith("error") for r in rows)
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=200)
    parser.add_argument("--unique", type=int, default=20, help="distinct synthetic images")
    parser.add_argument("--checkpoint", help="model weights (default: the shipped model)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--runtimes", nargs="+", choices=RUNTIMES, default=["torch"],
                        help="cupnet predict --runtime values to run each configuration with")
    parser.add_argument("--size", type=int, default=SIZE, help="the images' side (px)")
    parser.add_argument("--synth-size", type=int, default=SYNTH_SIZE,
                        help="the side (px) the images are rendered at, then resized to --size")
    args = parser.parse_args()
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="cupnet-bench-") as tmp:
        root = Path(tmp)
        images, meta = make_folder(root, args.images, min(args.unique, args.images), args.seed,
                                   args.size, args.synth_size)
        # (speed preset, overlays): the default both ways, then each preset with overlays
        runs = [(None, False), (None, True), *((preset, True) for preset in SPEED_PRESETS)]
        results = {}
        for runtime in args.runtimes:
            for preset, overlays in runs:
                out = root / (f"out_{runtime}_{preset or 'default'}_"
                              f"{'overlays' if overlays else 'plain'}")
                results[runtime, preset, overlays] = measure(images, meta, out, overlays,
                                                             args.checkpoint, preset, runtime)
    rows = []
    for (runtime, preset, overlays), r in results.items():
        cpu_per_image = r["cpu_s"] / r["images"]
        rows.append([runtime, f"--{preset}" if preset else "default",
                     "on" if overlays else "off", r["images"], r["cups"], r["errors"],
                     r["run_s"], r["images"] / r["run_s"], cpu_per_image,
                     os.cpu_count() / cpu_per_image, r["peak_rss_mb"], r["startup_s"]])
    table = markdown_table(["runtime", "speed preset", "overlays", "images", "cups found",
                            "error rows", "run (s)", "images / s", "CPU s / image",
                            "images / s if cores were free",
                            "peak memory (MB)", "process start-up (s)"], rows)
    command = (f"--images {args.images} --unique {args.unique} --runtimes "
               f"{' '.join(args.runtimes)}")
    if (args.size, args.synth_size) != (SIZE, SYNTH_SIZE):
        command += f" --size {args.size} --synth-size {args.synth_size}"
    rendered = ("as rendered" if args.size == args.synth_size
                else f"rendered at {args.synth_size} px and resized")
    body = "\n".join([
        "## cupnet predict: throughput and memory"
        + ("" if args.size == SIZE else f" at {args.size} px"),
        "",
        f"`.venv/bin/python -m benchmarks.predict {command}` on {machine()}; "
        f"load average {load:.1f} when started (the machine's cores may be shared). "
        f"Folder: {args.images} PNGs ({args.unique} distinct), {args.size} x {args.size}, "
        f"16-bit (synthetic, CT anatomy, {rendered}); "
        f"model: {args.checkpoint or 'shipped default'}; predict's defaults (batches of 8, "
        "two in flight, one PyTorch thread each). 'run' is end to end "
        "(reading, network, pose, CSV/JSON, overlays when on) after the process's one-off "
        "start-up (imports, model load, first-call set-up), which is listed apart. 'if cores "
        "were free': CPU cores / CPU seconds per image, an upper bound.",
        "",
        table,
    ])
    print(body)
    write_section("predict" if args.size == SIZE else f"predict_{args.size}", body)


if __name__ == "__main__":
    main()
