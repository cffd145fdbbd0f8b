"""``python -m place3d_app ARGS`` is the ``place3d`` command."""

from place3d_app import run

run()
