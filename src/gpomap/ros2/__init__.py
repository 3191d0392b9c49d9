"""gpomap on a ROS 2 robot: an rclpy node over the streaming mapper (``gpomap-ros2``, ``python -m gpomap.ros2``).

- :mod:`gpomap.ros2.poses`: odometry poses by time, the laser's pose at a scan's stamp.
- :mod:`gpomap.ros2.queries`: the render and query requests (no custom service types).
- :mod:`gpomap.ros2.node`: the rclpy wiring (subscriptions, publishers, services, parameters).

The middleware-free core is the ROS 1 node's (:mod:`gpomap.ros.live`, :mod:`gpomap.ros.messages`).
Importing this package does not import rclpy; ``pip install "gpomap[ros2]"`` installs it.
"""
