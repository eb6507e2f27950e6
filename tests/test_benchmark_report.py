"""Benchmark reports: sections rewritten in place, and another checkpoint's figures kept
apart from the shipped model's."""

from __future__ import annotations

from benchmarks.model import output_paths
from benchmarks.report import DOC, HEADER, markdown_row, markdown_table, write_section
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
