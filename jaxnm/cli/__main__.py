"""``python -m jaxnm.cli``: the ``jaxnm`` command."""

import sys

from . import main

sys.exit(main())
