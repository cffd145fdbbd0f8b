"""The commands of ``place3d``, one module each."""
