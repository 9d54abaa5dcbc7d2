"""Execution: how episodes fly, one by one or many at once, and where.

Layered, each module importing only those above it in this list:

* ``transport`` — the name of a flight's path to the simulator (in process or MAVLink);
* ``rollout`` — in-process episodes (one, or many in worker processes);
* ``fly`` — one run of episodes through a SITL + companion pair over UDP;
* ``backend`` — :class:`~training.exec.backend.Backend`, which runs those tasks, and the local
  backend; ``ray_backend`` — the same on a Ray cluster;
* ``choose`` — which backend a command's flags ask for; ``fly_many`` — many runs of SITL +
  companion pairs on a backend.
"""
