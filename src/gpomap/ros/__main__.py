"""``python -m gpomap.ros``: run the ROS 1 mapping node (see :mod:`gpomap.ros.node`)."""

import sys

from gpomap.ros.node import main

sys.exit(main())
