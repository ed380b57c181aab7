"""``python -m artnvg_core``: the command line of :mod:`artnvg_core.cli.main`."""

import sys

from .cli.main import main

sys.exit(main(whole_process=True))
