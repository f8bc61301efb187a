"""The ``scatmodes`` command line (:mod:`compress.cli.commands`) and its ``demo``.

What the demo shows is in :mod:`compress.cli.demo`. Run the command as ``scatmodes ...`` or
``python -m compress.cli ...``.
"""

from .commands import MODEL_EXAMPLES, main, model_classes, parse_model

__all__ = ["MODEL_EXAMPLES", "main", "model_classes", "parse_model"]
