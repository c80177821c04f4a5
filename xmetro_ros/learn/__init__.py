"""Training, evaluation and export of the model sets (docs/learning.md): model families and their search spaces,
the study protocol (point and cloud splits), fitting and ONNX export with the card, the study itself (tables,
SHAP, deviation maps), conformal calibration of U and the multivariate and shape domains, the uncertainty
acceptance experiment, warm-start priors. Needs the ``[train]`` extra (PyTorch, CatBoost, scikit-learn, shap);
nothing on the node's live path imports it.

May import: scan, preprocess, sim, judge, calibrate.
"""
