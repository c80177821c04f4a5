"""xmetro_ros: per-point error prediction for laser line scanners, over ROS 2.

Pure computation (geometry, simulator, features, models, closed loop) lives in ROS-free modules; the node and the
bag tools wire them to ROS 2 topics and MCAP files. Units inside: millimetres, milliseconds; on ROS topics: SI.
"""

__version__ = "0.1.0"
