"""The demo's helpers, now in :mod:`compress.cli.demo`.

This module keeps the old import path working for code written against scatmodes 0.1.
"""

from .cli.demo import *  # noqa: F403
from .cli.demo import __all__  # noqa: F401
