"""xmetro_ros.loop: close the loop on measured data (issue #7; docs/closed-loop.md).

``inputs.load_inputs`` → ``LoopData``; ``run.run_loop`` (model → residual → ``trace.trace_candidates`` → correction
from ``correct``, a retrained feature, or a phase-locked periodic correction of scan time that
transfers to held-out clouds (``periodic``) → before/after); ``report.write_report``; ``export.export_loop_model``;
inputs on Dask workers in ``inputs_dask``; CLI ``xmetro loop`` in ``xmetro_ros.apps.loop``.

May import: scan, preprocess, judge, calibrate, learn.
"""
