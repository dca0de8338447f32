"""Option names in the library's messages written as the command line's flags."""

from __future__ import annotations

__all__ = ["as_flags"]


def as_flags(text: str, names) -> str:
    """``text``, an options dataclass's error message, with the option names ``names`` written
    as the flags that set them (``max_steps`` -> ``--max-steps``): a name that opens the
    message, and a name with an underscore wherever it appears (no plain word has one)."""
    for name in names:
        if text.startswith(name + " "):
            text = f"--{name.replace('_', '-')}{text[len(name):]}"
    for name in names:
        if "_" in name:
            text = text.replace(name, f"--{name.replace('_', '-')}")
    return text
