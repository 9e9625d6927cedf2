"""``python -m tether``: the same entry point as the ``tether`` command."""

from tether.entry import main

main()
