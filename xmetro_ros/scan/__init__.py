"""The shared vocabulary of every other package: a ``Scan`` (points in mm, settings, head pose, artifact), the
scanner model and its settings, the head geometry (L, V, stand-off; head rotations), the nominal artifacts (sphere,
cylinder, plane, any triangle mesh, the generated test parts) and their specifications, least-squares fits, the
per-axis targets (nominal − measured), the loaders of the real measured data and the packaged resources (config,
shipped models). Scans from profile streams: a transform buffer (tf without ROS, ``tf_buffer.py``) and the assembly
of single profiles with their sensor poses into organized scans (``assembly.py``).

It owns no processing: no pre-processing, no model, no ROS. Meshes live here, not in ``parts``, because a mesh is
an artifact like a sphere: the virtual scanner scans it and a ``Scan`` records it.

May import: compute.
"""
