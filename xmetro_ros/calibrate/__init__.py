"""From recordings to learning data: the calibration campaign file (``xmetro-campaign/1``) and its recordings
checked and placed, the learning table (features, targets, oracle per point; study and cloud splits) built locally
or on Dask workers, and the VDI/VDE 2634-2 figures of a campaign. ``xmetro calibrate`` drives it with ``learn``.

May import: scan, preprocess, judge.
"""
