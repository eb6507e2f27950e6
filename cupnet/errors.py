"""What went wrong, in one line, for messages and error rows."""

from __future__ import annotations


def error_reason(error: BaseException) -> str:
    """The first line of ``error``'s message, or its type's name where it has none."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def whole_reason(error: BaseException, limit: int | None = None) -> str:
    """All of ``error``'s message on one line (a decoder's or an unpickler's runs over
    several, the cause in a later one), cut to ``limit`` characters, or its type's name
    where it has none."""
    return " ".join(str(error).split())[:limit] or type(error).__name__


def named_error(error: BaseException) -> str:
    """``error``'s type and :func:`error_reason`, for a failure no check foresaw (the type
    says more than the message of a library's own bug)."""
    return f"{type(error).__name__}: {error_reason(error)}"
