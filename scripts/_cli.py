"""What the scripts' command lines share: errors as one line, and outputs checked first.

A study or benchmark runs for minutes; an output it could not write is named before the
work (`output`), and a bad option or file is one line and exit 2 (`run`), as with the
``jaxnm`` command.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["run_script", "output"]


def run_script(main) -> int:
    """``main()``, a script's entry point, with its `ValueError`, `OSError` and `ImportError`
    printed as ``SCRIPT: error: ...`` (exit 2); its own exit code where it returns an int,
    else 0."""
    prog = os.path.basename(sys.argv[0]) or "script"
    try:
        code = main()
    except (ValueError, OSError, ImportError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    return code if isinstance(code, int) else 0


def output(flag: str, path, *, folder: bool) -> Path | None:
    """``path``, the output that ``flag`` names (None: none asked for), as a `Path`; a
    ValueError naming the flag where nothing could be written there (the ``jaxnm`` command's
    own check)."""
    if path is None:
        return None
    from jaxnm.cli._flags import output_path

    return output_path(flag, path, folder=folder)
