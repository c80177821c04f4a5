"""The one processing path of a scan: ``ScanHandler.process`` (cap → pre-process → features → model routing → ONNX
Runtime → flags and decision classes → summary) and what it is made of — per-point features, ``ModelSet``
inference with U and domains, the flag bits and verdict rules, the compiled set kernels and summary statistics,
PointNet point sets — plus the explanation of a judged scan (permutation SHAP, the judged-scan history behind
``~/explain``). The node's live path: no PyTorch, no training library.

May import: scan, preprocess, compute.
"""
