"""The firmware bridge: Twist commands from zenoh to an ArduPilot Rover over MAVLink, with its
own failsafe (docs/bridge.md). Onboard code: numpy, pymavlink, zenoh and rosbags, never torch."""
