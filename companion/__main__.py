"""``python -m companion``: the companion process (learned-policy checkpoints)."""

import sys

from companion.app import main

sys.exit(main())
