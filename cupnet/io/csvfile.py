"""The text of the CSV files a user gives (meta.csv, landmark files, truth and results).

Read as UTF-8 with Excel's byte-order mark dropped; a file in another encoding (Excel's
"CSV" on Windows writes the system's code page) is an error that names it, where the
decoder's own message named neither the file nor the fix.
"""

from __future__ import annotations

import io
from pathlib import Path


def csv_text(path: Path) -> io.StringIO:
    """``path``'s text for :mod:`csv`'s readers (line endings as written, so that a quoted
    cell may hold one).

    Raises:
        ValueError: the file is not UTF-8 text, naming it and the first bad byte.
    """
    try:
        text = Path(path).read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason}); save it as "
                         "UTF-8 (Excel: 'CSV UTF-8')") from None
    return io.StringIO(text, newline="")
