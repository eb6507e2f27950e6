"""review.html: every results row once, in its group, what needs a look first."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from cupnet.cli import main
from cupnet.io.results import SD_COLUMNS
from cupnet.io.review import GROUPS, review_page, row_group
from cupnet.predict import summarise

POSE = {"anteversion_deg": 21.5, "inclination_deg": 40.25, "k_mm": -3.0, "l_mm": 4.0,
        "h_mm": 250.0}
ALT = {"alt_anteversion_deg": 24.0, "alt_inclination_deg": 38.0, "alt_k_mm": -3.1,
       "alt_l_mm": 4.1, "alt_h_mm": 260.0}


def record(name: str, *rows: dict, overlay: str | None = None) -> dict:
    out = {"image": name, "rows": [{"image": name, **row} for row in rows]}
    if overlay:
        out["overlay"] = overlay
    return out


def sections(page: str) -> dict[str, str]:
    """Each group's table, by the group's key."""
    found = re.findall(r"<h2 id='(\w+)'>.*?</h2>\s*<table>(.*?)</table>", page, re.S)
    return dict(found)


def test_rows_are_grouped_in_order_of_need_and_each_shown_once() -> None:
    records = [
        record("fine.png", {"cup": 0, "status": "ok", "doubt": 0.4, "check": 0, **POSE}),
        record("blank.png", {"cup": None, "status": "no_cup"}),
        record("two.png", {"cup": 0, "status": "ok", "check": 0, **POSE},
               {"cup": 1, "status": "ambiguous", "check": 1, "doubt": 2.5, **POSE, **ALT}),
        record("broken.dcm", {"cup": None, "status": "error: cannot read file (truncated)"}),
        record("pair.png", {"cup": 0, "status": "ambiguous", "check": 0, **POSE, **ALT}),
    ]
    page = review_page(records, summarise(records))
    # Each heading, in the order of GROUPS, counts its group's rows.
    counts = {"check": 1, "error": 1, "ambiguous": 1, "ok": 2, "no_cup": 1}
    assert re.findall(r"<h2 id='(\w+)'>.*?\((\d+)\)</h2>", page) == [
        (key, str(counts[key])) for key, _ in GROUPS]
    tables = sections(page)
    assert "two.png" in tables["check"] and "2.50" in tables["check"]  # the doubt
    assert "broken.dcm" in tables["error"] and "truncated" in tables["error"]
    assert "pair.png" in tables["ambiguous"] and "24.00" in tables["ambiguous"]  # alt pose
    assert "fine.png" in tables["ok"] and "two.png" in tables["ok"]  # its other cup
    assert "<td>0</td>" in tables["ok"]  # cup 0 is shown, not blank
    assert "blank.png" in tables["no_cup"]
    assert sum(t.count("<tr>") - 1 for t in tables.values()) == 6  # each row once
    assert "<h1>cupnet predict: 5 images, 4 cups</h1>" in page


def test_given_landmarks_poses_show_their_standard_errors() -> None:
    """A row with standard errors shows each after its value; a row without shows the
    value alone, as does a blank error."""
    errors = dict(zip(SD_COLUMNS, (0.43, 0.61, 0.12, 0.15, 3.4), strict=True))
    records = [record("clicked.png", {"cup": 0, "status": "ok", "check": 0, **POSE, **errors}),
               record("found.png", {"cup": 0, "status": "ok", "check": 0, **POSE,
                                    "anteversion_sd_deg": None})]
    rows = sections(review_page(records, summarise(records)))["ok"].split("<tr>")[2:]
    assert "&plusmn; 0.43</td>" in rows[0] and "&plusmn; 3.40</td>" in rows[0]
    assert "&plusmn;" not in rows[1]


def test_rows_read_back_from_the_csv_group_the_same() -> None:
    """On --resume the earlier rows are strings (blank cells None)."""
    as_read = {"cup": "0", "status": "ok", "check": "1", "doubt": "1.9"}
    assert row_group(as_read) == row_group({"cup": 0, "status": "ok", "check": 1}) == "check"
    assert row_group({"status": "ok", "check": "0"}) == "ok"
    assert row_group({"status": "no_cup", "check": None}) == "no_cup"
    # A status no run writes (a hand-edited file) is shown among the failures, not hidden.
    assert row_group({"status": "weird", "check": "0"}) == row_group({"status": None}) == "error"


def test_names_are_escaped_and_overlay_links_quoted() -> None:
    name = "a<b>&c?.png"
    page = review_page([record(name, {"cup": None, "status": "no_cup"},
                               overlay="overlays/a<b>&c?.png")], {"images": 1, "cups": 0})
    assert "a&lt;b&gt;&amp;c?.png" in page and "<b>" not in page
    assert 'href="overlays/a%3Cb%3E%26c%3F.png"' in page


def test_predict_writes_the_page_beside_the_results(tmp_path: Path,
                                                    blind_checkpoint: Path) -> None:
    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "blank.png"), np.zeros((256, 320), np.uint8))
    (images / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    out = tmp_path / "out"
    assert main(["predict", str(images), "--out", str(out), "--checkpoint",
                 str(blind_checkpoint), "--assume-defaults", "--quiet"]) == 0
    page = (out / "review.html").read_text()
    tables = sections(page)
    assert list(tables) == ["error", "no_cup"]
    assert "broken.png" in tables["error"] and "blank.png" in tables["no_cup"]
    for link in re.findall(r'src="([^"]+)"', page):
        assert (out / link).is_file()
    assert len(re.findall(r'src="', page)) == 1  # the image that was read has its overlay
