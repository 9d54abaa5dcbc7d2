"""The autopilot inside the SITL: the PX4-like profile (:mod:`~sitl_sim.autopilot.px4`), the
ArduCopter profile, their parameter tables, AUTO.LAND's controller, and AUTO.PRECLAND's own
estimate and precision land."""
