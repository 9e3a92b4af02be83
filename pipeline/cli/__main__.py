"""``python -m crossfield.cli``: the ``crossfield`` command."""

import sys

from crossfield.cli import main

sys.exit(main())
