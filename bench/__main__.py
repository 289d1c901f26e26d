"""``python -m bench [CASE ...]``: see :mod:`bench`."""
import sys

from bench import main

if __name__ == "__main__":  # not when a spawned worker process imports it
    sys.exit(main())
