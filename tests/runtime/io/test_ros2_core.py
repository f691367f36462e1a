"""The core without the extras: importing the CLI, the session and replay loads neither
rclpy nor mcap (they are imported on use), so `ceilrun --help` and a plain run work
without `ceilkit[ros2]` / `ceilkit[mcap]`."""

from __future__ import annotations

import subprocess
import sys

CHECK = """
import sys
import ceilkit.cli.ceilrun, ceilkit.runtime.session, ceilkit.runtime.replay
import ceilkit.runtime.io.ros2, ceilkit.runtime.io.mcap_rec
loaded = sorted(m for m in sys.modules if m.split('.')[0] in
                ('rclpy', 'mcap', 'mcap_ros2', 'geometry_msgs', 'nav_msgs'))
print(','.join(loaded))
"""

BLOCKED = """
import sys
for m in ('rclpy', 'mcap', 'mcap_ros2', 'geometry_msgs', 'nav_msgs', 'diagnostic_msgs'):
    sys.modules[m] = None      # as if the extras were not installed
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.ros2 import Ros2Node
try:
    Ros2Node().open()
except ConfigError as exc:
    print(exc)
sys.argv = ['ceilrun', '--help']
from ceilkit.cli.ceilrun import main
main()
"""


def test_the_core_imports_neither_rclpy_nor_mcap():
    out = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == ""


def test_without_the_extras_help_works_and_the_node_says_what_to_install():
    out = subprocess.run([sys.executable, "-c", BLOCKED], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "ceilkit[ros2]" in out.stdout
    assert "--ros2" in out.stdout and "Usage: ceilrun" in out.stdout
