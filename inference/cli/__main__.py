"""``python -m npbrs.inference.cli``: the ``npbrs`` command."""

import sys

from .main import main

sys.exit(main())
