"""gpomap on a robot: a ROS 1 node over the streaming mapper (``gpomap-ros``, ``python -m gpomap.ros``).

- :mod:`gpomap.ros.messages`: LaserScan -> :class:`~gpomap.scans.Scan`, map -> OccupancyGrid
  layers; pure functions, no ROS library needed.
- :mod:`gpomap.ros.live`: the middleware-free core of a mapping node (scans wait for their
  pose, feed the mapper; grids and saved maps out).
- :mod:`gpomap.ros.node`: the rospy wiring (subscriptions, tf2, publishers, save service).

Importing this package does not import rospy.
"""
