"""Reading back the markdown tables the benchmark scripts write (imported as
`markdown_tables`, as `cup_cases` is)."""

from __future__ import annotations


def table_cells(text: str, first_header: str) -> list[list[str]]:
    """The cells of the markdown table in ``text`` whose header starts ``| first_header |``:
    the header's first, then each row's (the separator line left out)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header} |"))
    rows = []
    for line in [lines[start], *lines[start + 2:]]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip("|").split("|")])
    return rows
