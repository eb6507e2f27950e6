"""Pose solver throughput: poses per second by batch size, threads and stage.

Landmarks: the paper's protocol (see ``benchmarks/numsim.py``), 100 per cup, 1 px Gaussian
noise. Reports wall-clock poses/s and poses per CPU-second (all threads of the process),
best of ``--repeats`` runs, for: the direct ellipse fit alone, fit + closed form, and the full
solver (fit + closed form + maximum-likelihood refinement), eager and with its inner loop
through ``torch.compile`` (``compiled=True``; compilation happens in the warm-up call).

Run: ``.venv/bin/python -m benchmarks.solver_speed``
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch

from benchmarks.numsim import DIAMETER, GEOMETRY, landmarks, rim_parameters, sample_poses
from benchmarks.report import machine, markdown_table, write_section
from cupnet.ellipse import fit_ellipse
from cupnet.pose import solve_pose


def best_rate(fn: Callable[[], object], items: int, repeats: int) -> tuple[float, float]:
    """(wall poses/s, poses per CPU-second), best of ``repeats``."""
    wall, cpu = [], []
    for _ in range(repeats):
        start, cpu_start = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - cpu_start)
    return items / min(wall), items / min(cpu)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 100, 10000])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    gen = torch.Generator().manual_seed(0)
    rows = []
    for batch in args.batches:
        truth = sample_poses(batch, gen)
        points = landmarks(truth, rim_parameters(batch, 360.0, gen), 1.0, False, gen)
        stages = {
            "ellipse fit": lambda p=points: fit_ellipse(p, on_error="flag"),
            "fit + closed form": lambda p=points: solve_pose(p, GEOMETRY, DIAMETER, refine=False,
                                                             on_error="flag"),
            "full solver": lambda p=points: solve_pose(p, GEOMETRY, DIAMETER, on_error="flag"),
            "full solver, compiled": lambda p=points: solve_pose(p, GEOMETRY, DIAMETER,
                                                                 on_error="flag", compiled=True),
        }
        for threads in args.threads:
            torch.set_num_threads(threads)
            # Inductor fixes a kernel's thread count when it compiles it: compile anew.
            torch.compiler.reset()
            for name, fn in stages.items():
                fn()  # warm-up
                wall, cpu = best_rate(fn, batch, args.repeats)
                rows.append([batch, threads, name, f"{wall:,.0f}", f"{cpu:,.0f}"])
                print(rows[-1], flush=True)
    body = "\n".join([
        "## Pose solver throughput — `benchmarks/solver_speed.py`",
        "",
        f"Command: `.venv/bin/python -m benchmarks.solver_speed`; {machine()}. 100 landmarks "
        "per cup, 1 px noise, the paper's pose ranges; float64. `poses/CPU-s` divides by the "
        "CPU time of all the process's threads, the fairer figure when other work shares "
        "the machine. `compiled`: `solve_pose(..., compiled=True)`, the refinement's inner "
        "loop fused by `torch.compile` (a one-off compilation of about a minute, cached on "
        "disk; not timed).",
        "",
        markdown_table(["batch", "threads", "stage", "poses/s", "poses/CPU-s"], rows),
    ])
    print(body)
    write_section("solver_speed", body)


if __name__ == "__main__":
    main()
