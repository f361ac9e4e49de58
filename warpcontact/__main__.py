"""``python -m warpcontact``: the ``warpcontact`` command (``cli.main``)."""

import sys

from .cli import main

sys.exit(main())
