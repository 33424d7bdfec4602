"""Test configuration: make the workspace's Python packages importable from source.

The pure-numpy core is tested straight from ``ros_ws/src`` so that editing it needs no
rebuild; tests of nodes and of the graph use the colcon-built install tree, which
``scripts/test`` builds first.
"""

import pathlib
import sys

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
for package in ('wip_control', 'wip_sim'):
    path = str(REPO_ROOT / 'ros_ws' / 'src' / package)
    if path not in sys.path:
        sys.path.insert(0, path)
