"""Vigil: a drone swarm that keeps moving ground targets persistently localized."""

__version__ = "0.1.0"
