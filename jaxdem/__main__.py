"""``python -m jaxdem``: the same as the ``jaxdem`` command."""

from jaxdem.cli import entry

if __name__ == "__main__":
    entry()
