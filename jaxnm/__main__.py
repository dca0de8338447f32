"""``python -m jaxnm``: the ``jaxnm`` command, as ``python -m jaxnm.cli``."""

import sys

from .cli import main

__all__: list[str] = []

if __name__ == "__main__":
    sys.exit(main())
