"""volwarp: a command-line toolkit for modelling with sampled volumes."""

__version__ = "0.1.15"
