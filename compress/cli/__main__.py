"""``python -m compress.cli``: the same as the ``scatmodes`` console script."""

import sys

from .commands import main

sys.exit(main())
