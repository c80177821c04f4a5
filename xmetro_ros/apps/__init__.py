"""The command-line tools behind ``xmetro`` (:mod:`.cli`): simulate, train / export-default, record, replay,
predict, demo, loop, and the demo's HTML report. They drive the ROS layer (:mod:`xmetro_ros.ros`) and the core;
nothing imports them.

May import: scan, preprocess, sim, bag, judge, calibrate, plan, monitor, learn, loop, parts, ros, msg, srv, action.
"""
