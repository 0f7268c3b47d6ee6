"""Likeness: soft-skinned animatronic faces, from skin simulation to the realtime motor daemon."""

__version__ = "0.1.0"
