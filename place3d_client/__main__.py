"""``python -m place3d_client ARGS`` is the ``place3d`` command."""

import sys

from place3d_client import main

sys.exit(main())
