"""pytest, for the whole checkout: compress.mitsuba needs Mitsuba 3, so without it that
package's doctests are not collected (importing it raises the install hint)."""

import importlib.util

try:
    _HAS_MITSUBA = importlib.util.find_spec("mitsuba") is not None
except ValueError:  # sys.modules["mitsuba"] is None: blocked on purpose
    _HAS_MITSUBA = False

collect_ignore = [] if _HAS_MITSUBA else ["compress/mitsuba"]
