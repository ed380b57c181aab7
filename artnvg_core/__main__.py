"""``python -m artnvg_core``: the command line of :mod:`artnvg_core.cli.main`, as a whole process."""

from .cli.main import exit_without_teardown, main

exit_without_teardown(main(whole_process=True))
