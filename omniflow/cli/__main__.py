"""``python -m omniflow.cli`` is the ``omniflow`` command."""

import sys

from omniflow.cli import main

if __name__ == "__main__":
    sys.exit(main())
