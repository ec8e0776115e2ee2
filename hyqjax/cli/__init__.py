"""The ``hyqjax`` command line."""
from hyqjax.cli.app import main

__all__ = ["main"]
