"""Compute resources of the judge: :mod:`.threads`, the one thread budget that numba's parallel kernels, the model
set's ONNX runs and the numpy row blocks share (the node's ``threads``), and numba's threading layer, set before any
parallel kernel runs (every package with one imports this package); :mod:`.malloc`, glibc's allocator tuned for
scan after scan (the node at start).

May import: nothing of xmetro_ros.
"""
