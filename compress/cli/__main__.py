"""``python -m compress.cli``: the same as the ``scatmodes`` console script."""

import sys

from .commands import main

if __name__ == "__main__":
    sys.exit(main())
