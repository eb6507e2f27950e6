"""Shared by the benchmark scripts: print a markdown table and store it in docs/benchmarks.md.

Each benchmark owns one section of the file, delimited by HTML comments, and rewrites only
that section, so benchmarks can run in any order.
"""

from __future__ import annotations

import os
import platform
import re
import tempfile
from importlib import metadata
from pathlib import Path

import torch

DOC = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
HEADER = ("# Benchmarks\n\nWritten by the scripts in `benchmarks/`; each section says how to "
          "rerun it.\n")


def markdown_row(values: list[object]) -> str:
    """One row of a GitHub markdown table (floats to 4 significant digits)."""
    return "| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v)
                             for v in values) + " |"


def markdown_table(header: list[str], rows: list[list[object]]) -> str:
    """Rows of values -> a GitHub markdown table (floats to 4 significant digits)."""
    lines = [markdown_row(header), "|" + "---|" * len(header)]
    lines += [markdown_row(row) for row in rows]
    return "\n".join(lines)


# The libraries whose arithmetic the figures rest on besides torch: ONNX Runtime runs the
# networks, OpenCV and NumPy take part in synthesis and detection.
NUMERIC_LIBRARIES = ("onnxruntime", "opencv-python-headless", "numpy")


def processor(cpuinfo: str | None = None) -> str:
    """The CPU's model and its widest vector instructions, e.g. ``"AMD EPYC, AVX2"``, from
    ``/proc/cpuinfo``'s text (read where not given; the platform's name where it has
    none). The networks' float sums round with the kernels these choose, and the
    pipeline's discrete choices turn on such differences for the hard cups
    (docs/training.md, item 19): two machines' figures differ by that."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    fields = dict(line.split(":", 1) for line in cpuinfo.splitlines() if ":" in line)
    fields = {key.strip(): value.strip() for key, value in fields.items()}
    name = fields.get("model name") or platform.processor() or platform.machine()
    flags = set(fields.get("flags", "").split())
    widest = next((label for flag, label in (("avx512f", "AVX-512"), ("avx2", "AVX2"),
                                             ("avx", "AVX")) if flag in flags), None)
    return f"{name}, {widest}" if widest else name


def machine() -> str:
    """One line naming the machine and the libraries the figures come from."""
    parts = [f"{platform.machine()} ({processor()})", f"{os.cpu_count()} CPU cores",
             f"torch {torch.__version__}"]
    for name in NUMERIC_LIBRARIES:
        try:
            parts.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            continue
    return ", ".join([*parts, f"{torch.get_num_threads()} threads"])


def write_section(name: str, body: str, doc: Path = DOC, header: str = HEADER) -> None:
    """Replace (or append) the section ``name`` of ``doc`` (docs/benchmarks.md) with
    ``body``, atomically; a new file starts with ``header``."""
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    text = doc.read_text() if doc.exists() else header
    block = f"{begin}\n{body.strip()}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _: block, text)
    else:
        text = f"{text.rstrip()}\n\n{block}\n"
    doc.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=doc.parent, delete=False) as tmp:
        tmp.write(text)
    os.replace(tmp.name, doc)
