"""MCAP bags in rosbag2's format (``ros2 bag record -s mcap``): schemas, QoS metadata, writer, reader.

- :mod:`.schema`: ``ros2msg`` schema text with dependencies and RIHS01 type hashes from the installed interfaces.
- :mod:`.qos`: ``offered_qos_profiles`` as rosbag2 (metadata version 9) writes it; older forms normalised.
- :mod:`.qos_profiles`: the QoS our topics are offered with (plain dicts, no ROS import).
- :mod:`.writer`: :class:`~.writer.BagWriter` (bare ``.mcap`` or rosbag2 directory with split files).
- :mod:`.reader`: :class:`~.reader.BagReader` (reads what others write; recovers truncated/corrupted files).
- :mod:`.codec`: rclpy message objects ⇄ CDR bytes, imported on demand (the package's only contact with ROS).
- :mod:`.recover`: :func:`~.recover.recover` a killed recording into a complete, indexed bag.

Live recording over DDS is :mod:`xmetro_ros.ros.recorder`; the ``xmetro record`` and ``xmetro bag recover``
commands are :mod:`xmetro_ros.apps.record`.

May import: nothing of xmetro_ros.
"""
