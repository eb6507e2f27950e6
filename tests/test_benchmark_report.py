"""Benchmark reports: sections rewritten in place, and another checkpoint's figures kept
apart from the shipped model's."""

from __future__ import annotations

import argparse
from importlib import metadata

from benchmarks.model import FRESH_SEEDS, SELECTION_SEEDS, fresh_seed_intro, output_paths
from benchmarks.report import (
    DOC,
    HEADER,
    machine,
    markdown_row,
    markdown_table,
    write_section,
)
from cupnet.environment import processor
from cupnet.model import DEFAULT_CHECKPOINT


def test_sections_are_replaced_in_place_and_a_new_file_gets_its_header(tmp_path):
    doc = tmp_path / "b.md"
    write_section("one", "## One\n\nfirst", doc, header="# Mine\n")
    write_section("two", "## Two\n\nsecond", doc)
    write_section("one", "## One\n\nagain", doc)
    text = doc.read_text()
    assert text.startswith("# Mine\n")
    assert "first" not in text and text.index("again") < text.index("second")
    assert text.count("<!-- BEGIN one -->") == 1 and text.count("<!-- END two -->") == 1


def test_the_shipped_checkpoint_reports_to_docs_and_another_beside_itself(tmp_path):
    assert output_paths(str(DEFAULT_CHECKPOINT)) == (
        DOC, DOC.parent / "model_failures.png", HEADER)
    mine = tmp_path / "run" / "cupnet.safetensors"
    doc, gallery, header = output_paths(str(mine))
    assert (doc, gallery) == (mine.parent / "benchmarks.md", mine.parent / "model_failures.png")
    assert str(mine) in header and header != HEADER
    chosen = output_paths(str(mine), str(tmp_path / "d.md"), str(tmp_path / "g.png"))
    assert chosen[:2] == (tmp_path / "d.md", tmp_path / "g.png")


def test_a_table_is_its_header_a_rule_and_each_row_as_printed_alone():
    rows = [["detect", 1.234567, 8], ["batched", 2.0, "9 %"]]
    table = markdown_table(["pipeline", "ms", "found"], rows)
    assert table.splitlines() == ["| pipeline | ms | found |", "|---|---|---|",
                                  "| detect | 1.235 | 8 |", "| batched | 2 | 9 % |"]
    assert table.splitlines()[2:] == [markdown_row(row) for row in rows]


def test_the_fresh_seed_prose_gives_its_command_and_says_when_its_seeds_chose_settings():
    shipped = argparse.Namespace(checkpoint=str(DEFAULT_CHECKPOINT), fresh_seeds=FRESH_SEEDS,
                                 seed=20_261_123, fresh_images=180, sizes=[512, 768],
                                 eval_config="configs/synth_eval.yaml", seed_presets=[])
    honest = fresh_seed_intro(shipped, ["onnx"])
    assert "`python benchmarks/model.py --parts fresh --runtimes onnx`:" in honest
    assert "the honest estimate" in honest and "flatter" not in honest
    selection = argparse.Namespace(**{**vars(shipped), "checkpoint": "runs/x/cupnet.safetensors",
                                      "fresh_seeds": [SELECTION_SEEDS[0], FRESH_SEEDS[0]]})
    flattering = fresh_seed_intro(selection, ["onnx", "torch"])
    assert (f"--runtimes onnx torch --checkpoint runs/x/cupnet.safetensors --fresh-seeds "
            f"{SELECTION_SEEDS[0]} {FRESH_SEEDS[0]}`") in flattering
    assert f"of these seeds {SELECTION_SEEDS[0]} chose" in flattering
    assert "honest estimate" not in flattering
    # The fresh and the newer seeds' misses were looked at (items 42, 43): said, with the
    # item; the unseen seeds' were not.
    assert f"missed cups of seeds {', '.join(map(str, FRESH_SEEDS))} (docs/training.md, " \
           "item 42)" in honest
    newer = fresh_seed_intro(shipped, ["onnx"], "newer")
    assert newer.startswith("## CupNet on newer fresh seeds\n\n`python benchmarks/model.py "
                            "--parts newer --runtimes onnx`:")
    assert "item 43" in newer and "item 42" not in newer
    blind = fresh_seed_intro(shipped, ["onnx"], "blind")
    assert blind.startswith("## CupNet on blind seeds\n\n`python benchmarks/model.py "
                            "--parts blind --runtimes onnx`:")
    assert "item 44" in blind and "`--parts unseen` measures seeds nobody" in blind
    unseen = fresh_seed_intro(shipped, ["onnx"], "unseen")
    assert "the honest estimate" in unseen and "looking at the missed" not in unseen
    fast = fresh_seed_intro(argparse.Namespace(**{**vars(shipped), "seed_presets": ["fast"]}),
                            ["onnx"], "unseen")
    assert "`python benchmarks/model.py --parts unseen --runtimes onnx --seed-presets fast`:" \
        in fast


def test_the_machine_line_names_the_cpu_and_the_numeric_libraries():
    """Figures of the same code differ from one CPU to another (item 19): the line says which
    CPU and library versions gave them."""
    line = machine()
    assert f"({processor()})" in line
    assert f"onnxruntime {metadata.version('onnxruntime')}" in line
    assert f"numpy {metadata.version('numpy')}" in line and line.endswith(" threads")
