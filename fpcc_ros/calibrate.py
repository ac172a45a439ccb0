"""Choose a model's clustering defaults (score threshold θ, feature gate, screening factor γ,
the clustering mode and its fragment settings) on validation scenes.

θ and the gate are properties of a trained network (how high its center scores reach, how tight
its embeddings are), so they belong in its card, chosen on the trainer's own validation scenes
(never on evaluation data); γ depends on the part's shape (an elongated part's d_max is far
larger than the gap between parallel neighbours; the paper's ablation picks 0.8-1.0). The network
runs once per scene; every (θ, gate, γ) combination then reuses its outputs, since none changes
what the network sees.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fpcc_ros.evaluation import f1_score
from fpcc_ros.metrics import InstanceCounts, scene_counts, visible_threshold
from fpcc_ros.onnx_model import FpccModel
from fpcc_ros.pipeline import Pipeline, PipelineConfig, _StageClock


class _MemoModel:
    """The model's interface with outputs cached by input (same scene, same blocks)."""

    def __init__(self, model: FpccModel):
        self.card, self._model, self._cache = model.card, model, {}
        self.supports_global_stride = model.supports_global_stride

    def run(self, features: np.ndarray, knn: np.ndarray, global_stride: int = 1):
        key = (features.shape, features.tobytes()[:4096], float(features.sum()), int(knn.sum()),
               global_stride)
        if key not in self._cache:
            self._cache[key] = self._model.run(features, knn, global_stride=global_stride)
        return self._cache[key]


class _MemoPipeline(Pipeline):
    """A Pipeline that reuses the network points (valid, downsampled, floor marked) and block
    inputs (blocks, features, kNN) of the scene it last saw: they depend on the points and the
    voxel size only, not on the settings swept here. The network points were ~40% of the time
    per setting (a 12-scene ring screw calibration: downsampling 38 and floor 7 of ~125 ms)."""

    def __init__(self, model, config: PipelineConfig, cache: dict):
        super().__init__(model, config)
        self._cache = cache

    def _network_points(self, xyz: np.ndarray, clock: _StageClock):
        cfg = self.config
        key = ("points", xyz.shape, float(np.nansum(xyz[:64])), cfg.effective_voxel_size,
               cfg.max_points, cfg.remove_floor, cfg.view_axis, cfg.roi_min, cfg.roi_max,
               cfg.part_radius)
        if key not in self._cache:
            self._cache[key] = super()._network_points(xyz, clock)
        return self._cache[key]

    def _fragments(self, xyz, valid_idx, inverse, floor_free, num_network_points, view_axis,
                   image_shape=None):
        cfg = self.config
        key = ("fragments", len(valid_idx), len(floor_free), cfg.effective_voxel_size,
               cfg.fragment_eps, cfg.fragment_density, cfg.fragment_crease, cfg.part_radius,
               image_shape)
        if key not in self._cache:
            self._cache[key] = super()._fragments(xyz, valid_idx, inverse, floor_free,
                                                  num_network_points, view_axis, image_shape)
        return self._cache[key]

    def _block_inputs(self, xyz: np.ndarray, candidates: np.ndarray):
        key = (xyz.shape, len(candidates), candidates[:64].tobytes(), float(xyz[:64].sum()))
        if key not in self._cache:
            self._cache[key] = super()._block_inputs(xyz, candidates)
        return self._cache[key]


@dataclass
class CalibrationRow:
    score_threshold: float
    feature_gate: float
    counts: InstanceCounts
    screening_factor: float = 1.0
    center_merge: float = 0.0
    center_prototype: float = 0.0
    voxel_factor: float = 0.1
    part_counts: dict[str, InstanceCounts] = field(default_factory=dict)
    clustering: str = "paper"
    fragment_eps: float = 0.006
    fragment_density: int = 20
    fragment_min_points: int = 300
    fragment_join: float = 2.0
    fragment_crease: float = 0.0

    @property
    def f1(self) -> float:
        """F1 of the counts pooled over every scene."""
        return f1_score(self.counts)

    @property
    def part_mean_f1(self) -> float:
        """Mean over parts of each part's F1 (its scenes pooled).

        Pooled counts weigh parts by how many instances their scenes hold, so small parts
        (40 nuts to a pile) outvote long ones (15 shafts): on the default model's 14 built-in
        parts the pooled optimum chose γ 1.0, which merges neighbouring shafts. A default model
        must serve every part, so each part counts once.
        """
        if not self.part_counts:
            return self.f1
        return float(np.mean([f1_score(c) for c in self.part_counts.values()]))

    def score(self, objective: str) -> float:
        return self.part_mean_f1 if objective == "part-mean" else self.f1


def calibrate(model: FpccModel, scenes: list[Path], thresholds: list[float],
              gates: list[float], progress=None, screening_factors: list[float] | None = None,
              merges: list[float] | None = None, prototypes: list[float] | None = None,
              voxel_factors: list[float] | None = None, clusterings: list[str] | None = None,
              fragment_eps_values: list[float] | None = None,
              fragment_densities: list[int] | None = None,
              fragment_min_points: list[int] | None = None,
              fragment_joins: list[float] | None = None,
              fragment_creases: list[float] | None = None) -> list[CalibrationRow]:
    """Instance counts (visible protocol) for every combination, per part (the scenes'
    ``part_name``) and summed over ``scenes``;
    ``screening_factors`` / ``merges`` / ``prototypes`` / ``voxel_factors`` / ``clusterings``
    / ``fragment_*`` None keep the card's γ / center_merge / center_prototype / voxel_factor /
    clustering / fragment settings. The fragment settings are swept for the ``connected``
    clustering only (``paper`` has none).

    Each voxel factor runs the network again on every scene (what it sees changes); the other
    settings reuse its outputs, and the fragments are found once per fragment radius and
    density."""
    card = model.card
    factors = screening_factors or [card.screening_factor]
    merges = merges if merges is not None else [card.center_merge]
    prototypes = prototypes if prototypes is not None else [card.center_prototype]
    voxels = voxel_factors or [card.voxel_factor]
    fragment_settings = {
        "paper": [(card.fragment_eps, card.fragment_density, card.fragment_min_points,
                   card.fragment_join, card.fragment_crease)],
        "connected": list(itertools.product(fragment_eps_values or [card.fragment_eps],
                                            fragment_densities or [card.fragment_density],
                                            fragment_min_points or [card.fragment_min_points],
                                            fragment_joins or [card.fragment_join],
                                            fragment_creases if fragment_creases is not None
                                            else [card.fragment_crease]))}
    modes = [(cl, *f) for cl in (clusterings or [card.clustering]) for f in fragment_settings[cl]]
    rows: dict[tuple, dict[str, InstanceCounts]] = {
        key: {} for key in itertools.product(thresholds, gates, factors, merges, prototypes, voxels,
                                             modes)}
    memo = _MemoModel(model)
    inputs: dict = {}
    for path in (progress(scenes) if progress else scenes):
        scene = np.load(path)
        xyz = scene["points"].reshape(-1, 3)
        gt = scene["instance"].reshape(-1)
        finite = np.isfinite(xyz).all(axis=1)
        limit = visible_threshold(scene["points"].shape[0] * scene["points"].shape[1]) \
            if scene["points"].ndim == 3 else 300
        memo._cache.clear()
        inputs.clear()
        radius = float(scene["part_radius"])
        image = scene["points"].shape[:2] if scene["points"].ndim == 3 else None
        part = str(scene["part_name"]) if "part_name" in scene.files else ""
        for key in rows:
            t, g, f, m, p, v, (cl, fr, fd, fm, fj, fc) = key
            cfg = PipelineConfig.from_card(model.card, part_radius=radius, score_threshold=t,
                                           feature_gate=g, screening_factor=f, center_merge=m,
                                           center_prototype=p, voxel_factor=v, clustering=cl,
                                           fragment_eps=fr, fragment_density=fd,
                                           fragment_min_points=fm, fragment_join=fj,
                                           fragment_crease=fc)
            labels = _MemoPipeline(memo, cfg, inputs).segment(xyz, image).labels
            per_part = rows[key]
            per_part[part] = per_part.get(part, InstanceCounts()) + \
                scene_counts(labels[finite], gt[finite], "visible", limit)
    return [CalibrationRow(t, g, sum(parts.values(), InstanceCounts()), f, m, p, v, parts,
                           *mode) for (t, g, f, m, p, v, mode), parts in rows.items()]


# Fragment radii tried, when none are asked for, at the grid's best connected settings: each
# value in the grid itself multiplies it (the recipe's 15-22 minutes), a second pass at one
# setting costs seconds. What a model wants is its own: the 30-minute gear-shaft fine-tune
# scored validation F1 0.793 / 0.828 / 0.813 / 0.786 / 0.711 / 0.713 at 3 / 4 / 5 / 6 / 9 /
# 12 mm (20 test piles: 0.706 at 4 mm against 0.667 at the card's 6), the ring screw's kept
# 6 mm (0.750; 5 mm 0.747, 4 mm 0.735), ground truth wants 12-16 mm (README, connected). The
# 90-minute gear-shaft fine-tune: validation 0.847 -> 0.879 at 4 mm, test 0.709 -> 0.751.
REFINE_FRAGMENT_EPS = (0.004, 0.005, 0.006, 0.009, 0.012)


def refine_fragment_eps(model: FpccModel, scenes: list[Path], rows: list[CalibrationRow],
                        objective: str, progress=None,
                        eps_values: tuple[float, ...] = REFINE_FRAGMENT_EPS
                        ) -> list[CalibrationRow]:
    """``rows`` and, at the settings of their best ``connected`` row, one row per other fragment
    radius in ``eps_values``. Without a connected row, ``rows``."""
    return _refine_connected(model, scenes, rows, objective, progress, "fragment_eps",
                             "fragment_eps_values", eps_values)


# Joins tried, when none are asked for, at the best connected settings after the radius: a
# center's pieces are kept together while their bounding box's diagonal is at most this many
# d_max. A whole part's box can be longer than 2 d_max (a ring screw's diagonal: 2.36 d_max,
# median in the camera frame), and a model that places its centers well wants its parts whole:
# session 39's 30-minute ring-screw fine-tune scored validation F1 0.688 / 0.764 / 0.769 /
# 0.781 / 0.781 at 1.2 / 2 / 2.5 / 3 / 4, its 20 test piles 0.764 at 2 and 0.788 at 3 (left
# unlabelled 103 -> 43 parts); the shipped network, whose votes follow proximity more than
# identity, wants 1.2 (its card on the 20 IPA gear-shaft validation piles: 0.605 / 0.516 /
# 0.367 at 1.2 / 2 / 3).
REFINE_FRAGMENT_JOINS = (1.2, 2.0, 3.0)


def refine_fragment_join(model: FpccModel, scenes: list[Path], rows: list[CalibrationRow],
                         objective: str, progress=None,
                         joins: tuple[float, ...] = REFINE_FRAGMENT_JOINS
                         ) -> list[CalibrationRow]:
    """``rows`` and, at the settings of their best ``connected`` row, one row per other
    fragment join in ``joins``. Without a connected row, ``rows``."""
    return _refine_connected(model, scenes, rows, objective, progress, "fragment_join",
                             "fragment_joins", joins)


def _refine_connected(model: FpccModel, scenes: list[Path], rows: list[CalibrationRow],
                      objective: str, progress, name: str, keyword: str,
                      values: tuple[float, ...]) -> list[CalibrationRow]:
    """``rows`` and :func:`calibrate` at the best connected row's settings with the row's
    ``name`` setting (the ``keyword`` of :func:`calibrate`) at each other value of ``values``."""
    connected = [r for r in rows if r.clustering == "connected"]
    if not connected:
        return rows
    best = max(connected, key=lambda r: r.score(objective))
    new = [v for v in values if not np.isclose(v, getattr(best, name))]
    return rows + _around(model, scenes, best, progress, **{keyword: new}) if new else rows


# Voxel sizes (fractions of the part radius) tried, when none are asked for, at the best settings
# after the fragment radius: the network runs once more per value, seconds a scene. A thin part
# wants finer voxels than its card's 0.1 (the gear shaft: a median of 82 network points a part
# there). Session 38's 30-minute gear-shaft fine-tune, trained at 0.1, at its calibrated card:
# validation F1 0.829 / 0.852 / 0.870 / 0.846 / 0.817 at 0.1 / 0.08 / 0.07 / 0.06 / 0.05, the 20
# test piles 0.752 / 0.757 / 0.778 / 0.775 / 0.758, at 207 / 285 / 365 / 537 / 670 ms a scene
# (AMD EPYC, 2 vCPUs; voxel sizes rounded to 1 um: at the card's exact 0.1 the test piles
# score 0.741). 0.05 already loses, so the pass stops at 0.06.
REFINE_VOXEL_FACTORS = (0.1, 0.08, 0.07, 0.06)


def refine_voxel_factor(model: FpccModel, scenes: list[Path], rows: list[CalibrationRow],
                        objective: str, progress=None,
                        factors: tuple[float, ...] = REFINE_VOXEL_FACTORS
                        ) -> list[CalibrationRow]:
    """``rows`` and, at the settings of their best row, one row per other voxel factor in
    ``factors``."""
    best = max(rows, key=lambda r: r.score(objective))
    new = [f for f in factors if not np.isclose(f, best.voxel_factor)]
    return rows + _around(model, scenes, best, progress, voxel_factors=new) if new else rows


def _around(model: FpccModel, scenes: list[Path], best: CalibrationRow, progress,
            **changed: list) -> list[CalibrationRow]:
    """:func:`calibrate` at every setting of ``best`` but the ``changed`` ones (its keywords)."""
    settings = dict(screening_factors=[best.screening_factor], merges=[best.center_merge],
                    prototypes=[best.center_prototype], voxel_factors=[best.voxel_factor],
                    clusterings=[best.clustering], fragment_eps_values=[best.fragment_eps],
                    fragment_densities=[best.fragment_density],
                    fragment_min_points=[best.fragment_min_points],
                    fragment_joins=[best.fragment_join],
                    fragment_creases=[best.fragment_crease])
    return calibrate(model, scenes, [best.score_threshold], [best.feature_gate], progress,
                     **{**settings, **changed})


# (row attribute, `fpcc calibrate` option) of each swept setting, in the order the CLI lists them
SWEPT_SETTINGS = (("score_threshold", "--thresholds"), ("feature_gate", "--gates"),
                  ("screening_factor", "--screening"), ("center_merge", "--merges"),
                  ("center_prototype", "--prototypes"), ("voxel_factor", "--voxel-factors"),
                  ("clustering", "--clusterings"), ("fragment_eps", "--fragment-eps"),
                  ("fragment_density", "--fragment-densities"),
                  ("fragment_min_points", "--fragment-min-points"),
                  ("fragment_join", "--fragment-joins"),
                  ("fragment_crease", "--fragment-creases"))
OFF_AT_ZERO = ("center_merge", "center_prototype", "fragment_crease")   # 0 = the step is off


def settings_on_grid_edge(rows: list[CalibrationRow], best: CalibrationRow
                          ) -> list[tuple[str, str, float, str]]:
    """(setting, option, value, "largest" | "smallest") for each setting where ``best`` took the
    largest or smallest of several values tried: the optimum may lie beyond the grid.

    0 for center_merge and center_prototype means "off", a natural end of their range, and is
    not reported. On our per-part gear shaft and ring screw models the best θ (0.7) and gate
    (0.75) of the default grid both sat on its edge, and the gear shaft's γ (0.5) too.
    """
    edges = []
    for name, option in SWEPT_SETTINGS:
        if name == "clustering" or (name.startswith("fragment_") and best.clustering != "connected"):
            continue   # a choice, not a range; fragment settings only matter when connected
        tried = sorted({getattr(r, name) for r in rows if not name.startswith("fragment_")
                        or r.clustering == "connected"})
        value = getattr(best, name)
        if len(tried) < 2:
            continue
        if value == tried[-1]:
            edges.append((name, option, value, "largest"))
        elif value == tried[0] and not (value == 0 and name in OFF_AT_ZERO):
            edges.append((name, option, value, "smallest"))
    return edges
