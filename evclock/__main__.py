"""``python -m evclock``: the ``evclock`` command."""

from ._cli import main

main()
