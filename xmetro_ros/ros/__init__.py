"""The ROS 2 layer: everything that touches ROS message types or DDS (docs/architecture.md, "Layers").

PointCloud2 codec (:mod:`.cloud`), conversions (:mod:`.convert`, the one place for mm ⇄ m and stamps), message
building (:mod:`.messages`, :mod:`.output_clouds`), :class:`~.core.XmetroCore` (the node's computation without DDS),
parameters, diagnostics, the DDS environment, the node (:mod:`.node`), rclpy helpers, the recorder, ``Scan`` ⇄ MCAP
(:mod:`.scan_io`) and the node's outputs in bags (:mod:`.node_outputs`). May use the ROS-free core; never
``xmetro_ros.apps`` nor ``xmetro_ros.learn`` (test/test_layers.py).
"""
