"""The ``scatmodes`` command line (:mod:`compress.cli.commands`) and what its ``demo`` shows
(:mod:`compress.cli.demo`). Run it as ``scatmodes ...`` or ``python -m compress.cli ...``."""

from .commands import MODEL_EXAMPLES, main, model_classes, parse_model

__all__ = ["MODEL_EXAMPLES", "main", "model_classes", "parse_model"]
