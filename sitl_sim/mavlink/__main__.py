"""``python -m sitl_sim.mavlink``: the SITL as its own process (``visland sitl``'s flags)."""

import sys

from sitl_sim.mavlink.sitl import main

sys.exit(main())
