"""Contracts shared by the simulator, the learner, the controller and the firmware bridge.

Everything that crosses a boundary between those packages is defined here exactly once: the
action table, the lidar beam convention, the observation encoding and the settings machinery.
This package imports none of the others.
"""
