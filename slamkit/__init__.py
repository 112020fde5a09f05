"""slamkit: a plugin-based RGB-D SLAM framework (GS-ICP SLAM first)."""

__version__ = "0.1.0"

import os as _os

# Tracking (numpy, pykdtree) and mapping (torch) each use OpenMP; with the default spin-waiting
# their thread pools fight over the cores (measured: G-ICP 36 -> 86 ms per frame on 2 cores).
# Must be set before either runtime starts, hence here. A user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
