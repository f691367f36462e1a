"""ROS 2 files that install with ceilkit: a parameter file and a launch file.

``ceilkit.launch.py`` (``ros2 launch "$(python -c 'import ceilkit.configs.ros2 as r;
print(r.LAUNCH)')"``) runs ``ceilkit-ros2`` with ``ceilkit.params.yaml``; see
docs/integration.md.
"""

from pathlib import Path

HERE = Path(__file__).resolve().parent
PARAMS = HERE / "ceilkit.params.yaml"
"""The node's parameters with their defaults (``--ros-args --params-file``)."""
LAUNCH = HERE / "ceilkit.launch.py"
"""The Python launch file."""
