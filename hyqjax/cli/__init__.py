"""The ``hyqjax`` command line."""
from hyqjax.cli.app import console_main, main

__all__ = ["console_main", "main"]
