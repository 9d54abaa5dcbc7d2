"""The landing site: the ground's relief and the pad's motion, pure numpy (no rendering).

Drawn once per episode by :func:`sitl_sim.world.episode_world` into ``EpisodeWorld.site`` (None:
the nominal site, a still pad on flat ground at height 0) from the ``[terrain]`` section
(:mod:`sitl_sim.site.terrain`) and ``[pad]``'s motion keys (:mod:`sitl_sim.render.pad_section`,
drawn by :func:`sitl_sim.site.pad_motion.draw_pad_motion`). Frames: NED, metres, sim seconds;
heights are up positive (NED down = -height). The pad's centre starts above the world origin.

API (:class:`sitl_sim.site.site.Site`), cheap enough to query every physics step::

    site.ground_height(n, e) -> float          # terrain surface height (up, m): slope, relief,
                                               # craters, rocks; water: the mean level, 0
    site.ground_normal(n, e) -> (3,) tuple     # the ground's upward unit normal, NED
    site.pad_pose(t) -> PadPose                # position_ned (3,), R_pad_to_ned (3, 3),
                                               # velocity_ned (3,), omega_ned (3,): the centre
                                               # of the surface the pad lies on, at time t
    site.surface_height(n, e, t) -> float      # the highest surface at (n, e): ground, rock,
                                               # the vehicle's roof or deck at time t
    site.range_along(origin_ned, direction_ned, t, max_range) -> float
                                               # ray cast (radar): distance to the first
                                               # surface, inf if none within max_range
    site.record() -> dict                      # what was drawn, for the episode's log
    site.vehicle                               # the carrying vehicle's convex solids (pad frame)
    site.moves                                 # whether pad and vehicle move

Modules: ``terrain`` (the ``[terrain]`` section; slope plane, relief and craters on a 1 m
heightfield, rocks as half-ellipsoids, a ray march that cannot step through the ground),
``pad_motion`` (static, rover, deck), ``vehicle`` (rover, hull, platform as convex prisms),
``site`` (:class:`Site`, composing them).
"""
