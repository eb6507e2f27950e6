"""The CPU and library versions that benchmarks and results.json record."""

from __future__ import annotations

from importlib import metadata

from cupnet.environment import library_versions, processor

EPYC = "processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse2 avx avx2 fma\n"


def test_the_processor_is_named_with_its_widest_vector_instructions():
    assert processor(EPYC) == "AMD EPYC 7B13, AVX2"
    assert processor(EPYC.replace("avx2", "avx2 avx512f")) == "AMD EPYC 7B13, AVX-512"
    assert processor(EPYC.replace(" avx avx2", "")) == "AMD EPYC 7B13"


def test_a_cpuinfo_without_a_model_name_falls_back_to_the_platform():
    """Some kernels (ARM, containers) list no ``model name``: the line still names a CPU."""
    assert processor("processor : 0\nflags : avx\n").endswith(", AVX")
    assert processor("processor : 0\n")


def test_library_versions_are_the_installed_ones_and_skip_the_absent():
    versions = library_versions(("numpy", "no-such-distribution-cupnet"))
    assert versions == {"numpy": metadata.version("numpy")}
