"""Parts against their CAD: region types on a mesh, registration of a scan to the CAD (ICP), the deviation map
measured − CAD before / after compensation with U along the normal, and the generalisation studies on generated
parts (``parts.study``; ``parts.seen``: models trained with and without mesh parts, which needs the ``[train]``
extra). The meshes themselves and the generated parts are artifacts: ``xmetro_ros.scan``.

May import: scan, preprocess, sim, judge, calibrate, learn.
"""
