"""Shared by the benchmark scripts: print a markdown table and store it in docs/benchmarks.md.

Each benchmark owns one section of the file, delimited by HTML comments, and rewrites only
that section, so benchmarks can run in any order.
"""

from __future__ import annotations

import os
import platform
import re
import tempfile
from pathlib import Path

import torch

from cupnet.environment import library_versions, processor

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


def machine() -> str:
    """One line naming the machine and the libraries the figures come from."""
    parts = [f"{platform.machine()} ({processor()})", f"{os.cpu_count()} CPU cores",
             f"torch {torch.__version__}"]
    parts += [f"{name} {version}" for name, version in library_versions().items()]
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
