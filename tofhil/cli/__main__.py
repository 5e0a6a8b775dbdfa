"""``python -m tofhil.cli``: the same entry point as the ``tofhil`` script."""

from tofhil.cli import main

main()
