"""The ``jaxdea`` command line: one module per command group, shared parsing in :mod:`.args`."""

from .main import build_parser, main

__all__ = ["build_parser", "main"]
