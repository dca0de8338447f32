"""Option names in the library's messages written as the command line's flags, and the
outputs a flag names checked before a command's work."""

from __future__ import annotations

from pathlib import Path

__all__ = ["as_flags", "output_path"]


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


def output_path(flag: str, path, *, folder: bool = False) -> Path:
    """``path``, the output that ``flag`` names, as a `Path`; a ValueError naming the flag
    where nothing could be written there (`jaxnm.io.writable`): checked before the work,
    not found after it."""
    from ..io import writable

    try:
        return writable(path, folder=folder)
    except OSError as e:
        raise ValueError(f"{flag} {e}") from None
