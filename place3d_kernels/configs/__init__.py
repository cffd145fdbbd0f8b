"""Shipped configuration files (TOML): lidars/, placements/, scenes/, conditions/, optimize/."""
