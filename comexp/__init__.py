"""comexp: centre-of-mass estimation by dynamic pushing."""

__version__ = "0.1.0"
