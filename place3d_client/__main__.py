"""``python -m place3d_client ARGS`` is the ``place3d`` command."""

from place3d_client import run

run()
