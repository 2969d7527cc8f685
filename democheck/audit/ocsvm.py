"""The paper's linear one-class SVM on the training demos' precisions 1/sigma^2, stored as plain numbers in the
model's config.json: a column of the audit (``ocsvm_margin``) and a bench scorer (``ocsvm_flag``), beside the
ranking (``democheck.audit.scores``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from democheck.audit.scores import consistency, robust_stats
from democheck.petnet.posterior import TaskPosterior


def ocsvm_features(sigma: np.ndarray) -> np.ndarray:
    return 1.0 / np.maximum(sigma, 1e-6) ** 2


def fit_ocsvm(sigma: np.ndarray, nu: float = 0.01) -> dict[str, Any]:
    """Fit the linear one-class SVM on training demos' sigma vectors; returns JSON-able parameters."""
    from sklearn.svm import OneClassSVM

    x = ocsvm_features(sigma)
    scale = x.mean(0)  # features are precisions in the 1e2..1e8 range: put them near 1 for the solver
    svm = OneClassSVM(kernel="linear", nu=nu).fit(x / scale)
    return {"kernel": "linear", "feature": "precision", "nu": nu, "scale": scale.tolist(),
            "coef": svm.coef_.ravel().tolist(), "offset": float(svm.offset_[0]), "n_fit": int(len(x)),
            "flagged_fraction_on_fit": float((svm.decision_function(x / scale) < 0).mean())}


def ocsvm_margin(params: dict[str, Any], sigma: np.ndarray) -> np.ndarray:
    """Signed distance-like margin: negative = on the anomalous side of the hyperplane."""
    x = ocsvm_features(sigma) / np.asarray(params["scale"])
    return x @ np.asarray(params["coef"]) - params["offset"]


def reference(post: TaskPosterior, tasks: np.ndarray, nu: float = 0.01) -> dict[str, Any]:
    """What an audit of new data keeps from the training demos: the OCSVM, and their score scales (reported)."""
    return {"score": robust_stats(post.task_uncertainty()), "consistency": robust_stats(consistency(post, tasks)),
            "ocsvm": fit_ocsvm(post.sigma, nu)}
