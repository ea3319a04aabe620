"""``python -m sim_bridge``: see :mod:`sim_bridge.cli`."""

from __future__ import annotations

import sys

from sim_bridge.cli import main

sys.exit(main())
