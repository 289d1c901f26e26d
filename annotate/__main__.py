"""``python -m annotate``: see :mod:`annotate.server`."""
import sys

from annotate.server import main

sys.exit(main())
