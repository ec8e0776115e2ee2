"""``python -m hyqjax.cli COMMAND ...``: the ``hyqjax`` command line."""
import sys

from hyqjax.cli.app import main

sys.exit(main())
