"""``python -m hyqjax.cli COMMAND ...``: the ``hyqjax`` command line."""
from hyqjax.cli.app import console_main

console_main()
