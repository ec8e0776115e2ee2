"""Subcommands of the ``hyqjax`` CLI (see :mod:`hyqjax.cli`)."""
