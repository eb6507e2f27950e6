"""What went wrong, in one line, for messages and error rows."""

from __future__ import annotations


def error_reason(error: BaseException) -> str:
    """The first line of ``error``'s message, or its type's name where it has none."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__
