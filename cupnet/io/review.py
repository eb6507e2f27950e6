"""``review.html``: one page to check a ``cupnet predict`` run by eye, what needs a look first.

The rows of ``results.csv`` in groups, each a table with the image's overlay beside its pose:
the cups flagged ``check`` (the model doubts them, or their given landmarks lie off the
rim), the images that failed (``error: ...``), the ambiguous cups (two poses fit the
ellipse; the second in ``alt_*``), the other cups, and the images without a cup. A static
file (no script, nothing fetched) beside results.csv; the overlays load as the page is
scrolled.
"""

from __future__ import annotations

import html
from collections.abc import Iterable
from pathlib import Path
from urllib.parse import quote

from cupnet.io.results import ALT_COLUMNS, POSE_COLUMNS, SD_COLUMNS, atomic_write

# Group title and which rows it holds, in the order the page shows them.
GROUPS: tuple[tuple[str, str], ...] = (
    ("check", "Cups flagged check (the model doubts them, or their given landmarks lie off "
               "the rim): look before trusting them"),
    ("error", "Images that failed"),
    ("ambiguous", "Ambiguous cups: two poses fit the ellipse (the second is alt_*)"),
    ("ok", "Cups found"),
    ("no_cup", "Images without a cup"),
)
HEADINGS = ("overlay", "image", "cup", "status", "anteversion", "inclination", "k", "l", "h",
            "doubt")
STYLE = ("body{font-family:sans-serif;margin:1em}table{border-collapse:collapse}"
         "td,th{border:1px solid #ccc;padding:2px 6px;text-align:left;vertical-align:top}"
         "img{width:192px}.num{text-align:right;font-variant-numeric:tabular-nums}")


def row_group(row: dict) -> str:
    """The :data:`GROUPS` key of a results row (values as predict keeps them, or as strings
    read back from results.csv)."""
    status = str(row.get("status") or "")
    if str(row.get("check")) == "1":
        return "check"
    if status.startswith("error"):
        return "error"
    return status if status in ("ambiguous", "ok", "no_cup") else "error"


def _number(value: object, digits: int) -> str:
    try:
        return f"{float(value):.{digits}f}"  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return ""


def _cells(row: dict, overlay: str | None) -> str:
    link = html.escape(quote(overlay)) if overlay else ""  # a file name may hold '?' or '%'
    picture = (f'<a href="{link}"><img loading="lazy" alt="overlay" src="{link}"></a>'
               if overlay else "")
    pose = [_number(row.get(c), 2) for c in POSE_COLUMNS]
    # Standard errors where the row has them (given landmarks), after their values.
    pose = [f"{p} &plusmn; {e}" if p and e else p
            for p, e in zip(pose, (_number(row.get(c), 2) for c in SD_COLUMNS), strict=True)]
    if row.get("status") == "ambiguous":
        pose = [f"{p}<br>{_number(row.get(a), 2)}" for p, a in zip(pose, ALT_COLUMNS,
                                                                   strict=True)]
    cup = row.get("cup")
    cells = [picture, html.escape(str(row["image"])), "" if cup is None else html.escape(str(cup)),
             html.escape(str(row.get("status") or ""))]
    numbers = [*pose, _number(row.get("doubt"), 2)]
    return ("<td>" + "</td><td>".join(cells) + '</td><td class="num">'
            + '</td><td class="num">'.join(numbers) + "</td>")


def review_page(records: Iterable[dict], summary: dict) -> str:
    """The page's HTML: each record's rows grouped (:data:`GROUPS`), input order within a
    group; ``summary`` as :func:`cupnet.predict.summarise` gives it."""
    groups: dict[str, list[str]] = {key: [] for key, _ in GROUPS}
    for record in records:
        for row in record["rows"]:
            groups[row_group(row)].append(f"<tr>{_cells(row, record.get('overlay'))}</tr>")
    head = "<tr>" + "".join(f"<th>{h}</th>" for h in HEADINGS) + "</tr>"
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>cupnet predict: "
             f"review</title><style>{STYLE}</style></head><body>",
             f"<h1>cupnet predict: {summary['images']} images, {summary['cups']} cups</h1>",
             "<p>Poses in degrees (anteversion, inclination) and millimetres (k, l, h), "
             "with their standard errors where the landmarks were given; "
             "doubt: how little the rim network believes the pose (true poses mostly below "
             "1). Click an overlay for full size.</p>"]
    for key, title in GROUPS:
        if groups[key]:
            parts += [f"<h2 id='{key}'>{html.escape(title)} ({len(groups[key])})</h2>",
                      f"<table>{head}{''.join(groups[key])}</table>"]
    parts.append("</body></html>\n")
    return "\n".join(parts)


def write_review_page(path: Path, records: Iterable[dict], summary: dict) -> None:
    """:func:`review_page` written atomically to ``path``."""
    text = review_page(records, summary)
    atomic_write(path, lambda f: f.write(text))
