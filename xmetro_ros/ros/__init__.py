"""The ROS 2 layer: everything that touches ROS message types or DDS (docs/architecture.md, "Layers").

PointCloud2 codec (:mod:`.cloud`), a driver's single-profile message → ``scan.assembly.Profile``
(:mod:`.profile_msgs`), conversions (:mod:`.convert`, the one place for mm ⇄ m and stamps), message
building (:mod:`.messages`, :mod:`.output_clouds`), :class:`~.core.XmetroCore` (the node's computation without DDS),
parameters, diagnostics, the DDS environment, the node (:mod:`.node`), rclpy helpers, the recorder, ``Scan`` ⇄ MCAP
(:mod:`.scan_io`) and the node's outputs in bags (:mod:`.node_outputs`). Never the command-line tools, training
(``learn``, ``calibrate``) or the closed loop: the node does not load the training stack.

May import: scan, bag, judge, parts, plan, monitor, compute, msg, srv, action.
"""
