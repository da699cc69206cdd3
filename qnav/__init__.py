"""qnav: learn robot navigation cheaply in a batched simulator and run it on a real car."""

from qnav.gym_ids import register_when_gymnasium_loads

__version__ = "0.1.0"

register_when_gymnasium_loads()  # gymnasium.make("qnav/ObstaclesInertia-v0") after `import qnav`
