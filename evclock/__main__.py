"""``python -m evclock``: the ``evclock`` command."""

from evclock.tools._cli import main

main()
