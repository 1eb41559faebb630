"""``python -m arraysel``: the ``arraysel`` command (:func:`arraysel.cli.main.main`)."""
import sys

from arraysel.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
