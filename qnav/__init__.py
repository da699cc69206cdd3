"""qnav: learn robot navigation cheaply in a batched simulator and run it on a real car."""

__version__ = "0.1.0"
