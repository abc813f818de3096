"""``python -m mso`` is the ``mso`` command."""

from mso.cli import main

main()
