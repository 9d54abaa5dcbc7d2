"""The downward camera: the pybullet scene, the fast homography renderer, the ground and its
procedural terrain families, and the ``[visual]`` section drawn per episode."""
