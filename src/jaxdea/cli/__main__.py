"""``python -m jaxdea.cli ...``: the same as the ``jaxdea`` command."""

import sys

from .main import main

sys.exit(main())
