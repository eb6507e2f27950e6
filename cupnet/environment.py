"""What a run's figures rest on besides cupnet's own code: the CPU and the numeric libraries.

The networks' float sums round with the kernels that ONNX Runtime and oneDNN pick for the
CPU's vector instructions, and the pipeline's discrete choices turn on such differences for
the hard cups (docs/training.md, items 19 and 69): the same code and weights find a few cups
otherwise on another CPU or library release. Benchmarks and ``cupnet predict``'s
results.json record them for that reason.
"""

from __future__ import annotations

import platform
from importlib import metadata
from pathlib import Path

# The libraries whose arithmetic the poses rest on besides torch: ONNX Runtime runs the
# networks, OpenCV and NumPy take part in synthesis and detection.
NUMERIC_LIBRARIES = ("onnxruntime", "opencv-python-headless", "numpy")


def processor(cpuinfo: str | None = None) -> str:
    """The CPU's model and its widest vector instructions, e.g. ``"AMD EPYC, AVX2"``, from
    ``/proc/cpuinfo``'s text (read where not given; the platform's name where it has
    none)."""
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


def library_versions(names: tuple[str, ...] = NUMERIC_LIBRARIES) -> dict[str, str]:
    """``{distribution: version}`` of those of ``names`` that are installed."""
    versions = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions
