"""``python -m jaxdem``: the same as the ``jaxdem`` command."""

import sys

from jaxdem.cli import main

if __name__ == "__main__":
    sys.exit(main())
