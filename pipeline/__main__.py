"""``python -m pipeline``: see :mod:`pipeline.cli`."""
import sys

from pipeline.cli import main

if __name__ == "__main__":  # not when a spawned worker process imports it
    sys.exit(main())
