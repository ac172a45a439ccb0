"""Choose a model's clustering defaults (score threshold θ, feature gate) on validation scenes.

θ and the gate are properties of a trained network (how high its center scores reach, how tight
its embeddings are), so they belong in its card, chosen on the trainer's own validation scenes
(never on evaluation data). The network runs once per scene; every (θ, gate) pair then reuses
its outputs, since neither changes what the network sees.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fpcc_ros.metrics import InstanceCounts, scene_counts, visible_threshold
from fpcc_ros.onnx_model import FpccModel
from fpcc_ros.pipeline import Pipeline, PipelineConfig


class _MemoModel:
    """The model's interface with outputs cached by input (same scene, same blocks)."""

    def __init__(self, model: FpccModel):
        self.card, self._model, self._cache = model.card, model, {}

    def run(self, features: np.ndarray, knn: np.ndarray):
        key = (features.shape, features.tobytes()[:4096], float(features.sum()), int(knn.sum()))
        if key not in self._cache:
            self._cache[key] = self._model.run(features, knn)
        return self._cache[key]


@dataclass
class CalibrationRow:
    score_threshold: float
    feature_gate: float
    counts: InstanceCounts

    @property
    def f1(self) -> float:
        p, r = self.counts.precision, self.counts.recall
        return 2 * p * r / (p + r) if p + r else 0.0


def calibrate(model: FpccModel, scenes: list[Path], thresholds: list[float],
              gates: list[float], progress=None) -> list[CalibrationRow]:
    rows = {(t, g): InstanceCounts() for t, g in itertools.product(thresholds, gates)}
    memo = _MemoModel(model)
    for path in (progress(scenes) if progress else scenes):
        scene = np.load(path)
        xyz = scene["points"].reshape(-1, 3)
        gt = scene["instance"].reshape(-1)
        finite = np.isfinite(xyz).all(axis=1)
        limit = visible_threshold(scene["points"].shape[0] * scene["points"].shape[1]) \
            if scene["points"].ndim == 3 else 300
        memo._cache.clear()
        for t, g in rows:
            cfg = PipelineConfig.from_card(model.card, part_radius=float(scene["part_radius"]),
                                           score_threshold=t, feature_gate=g)
            labels = Pipeline(memo, cfg).segment(xyz).labels  # type: ignore[arg-type]
            rows[(t, g)] += scene_counts(labels[finite], gt[finite], "visible", limit)
    return [CalibrationRow(t, g, c) for (t, g), c in rows.items()]
