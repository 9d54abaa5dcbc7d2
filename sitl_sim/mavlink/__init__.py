"""The MAVLink SITL: the simulator behind a PX4-like (or ArduCopter-like) autopilot endpoint
over real UDP, composed of parts (:mod:`sitl_sim.mavlink.sitl` lists them).

``python -m sitl_sim.mavlink`` runs it with the flags of ``visland sitl``.
"""
