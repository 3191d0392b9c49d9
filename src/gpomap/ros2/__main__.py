"""``python -m gpomap.ros2``: run the ROS 2 mapping node (see :mod:`gpomap.ros2.node`)."""

import sys

from gpomap.ros2.node import main

sys.exit(main())
