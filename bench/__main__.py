"""``python -m bench [CASE ...]``: see :mod:`bench`."""
import sys

from bench import main

sys.exit(main())
