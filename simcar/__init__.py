"""The simulated car in the loop: network processes around the pure simulator (`sim`).

`car.SimCar` plays the car on zenoh (LaserScan and PoseStamped out, the world stepped with the
motion of a MAVLink vehicle); `mavlink_vehicle.MavlinkVehicle` is that vehicle, a small Rover-like
car speaking MAVLink (`qnav fake-vehicle`, the bridge's tests); `firmware_vehicle.FirmwareVehicle`
drives ArduPilot's own firmware in SITL instead. They import `sim` and `contracts`; `sim` imports
none of them, so the numpy world stays free of sockets and threads.
"""
