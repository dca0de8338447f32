"""mkdocs hooks (``hooks:`` in ``mkdocs.yml``): before the build, every tutorial notebook
has a current executed copy in ``docs/tutorials/`` (`scripts.docs.notebooks`)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # mkdocs imports this file by path, not as a package
    sys.path.insert(0, str(ROOT))

from scripts.docs import notebooks  # noqa: E402

log = logging.getLogger("mkdocs.hooks.notebooks")


def on_pre_build(config, **kwargs) -> None:
    """Execute the notebooks whose executed copy is missing or stale."""
    notebooks.ensure_executed(log=log.info)
