"""FPCC against the Euclidean-clustering baseline on labelled scenes (DESIGN.md §4b).

For every scene NPZ both methods segment the SAME points; counts are taken under the ``paper``
and ``visible`` protocols (fpcc_ros.metrics) and summed over the set before any ratio is formed.
The baseline runs at every tolerance of a sweep and is reported at its best one (best F1 of the
summed precision and recall, per protocol) -- the strongest version of it a user could tune, so
FPCC is never compared against a strawman. Timings are per scene, wall clock.
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from fpcc_ros.baseline import cluster_foreground, default_plane_tolerance, foreground_mask
from fpcc_ros.metrics import VISIBLE_MIN_POINTS, InstanceCounts, scene_counts, visible_threshold

PROTOCOLS = ("paper", "visible")
REPORT_FORMAT = "fpcc_ros/eval-report/1"
# Default baseline sweep as fractions of d_max: 0.002..0.02 m for a 0.1 m part. Below ~2 % the
# gaps between scan points split parts; above ~20 % every touching pair merges.
TOLERANCE_FRACTIONS = np.geomspace(0.02, 0.2, 7)
SELECTION_RULE = ("best F1 = 2PR/(P+R) of precision and recall summed over all scenes, per "
                  "protocol; ties go to the smaller tolerance")


class EvalError(ValueError):
    """The evaluation cannot run (no scenes, none with ground truth); the message says why."""


class SceneError(EvalError):
    """A scene file that does not follow DESIGN.md §4; the message names the file and the key."""


@dataclass
class Scene:
    """One scene's points (flat, NaN = no return) and ground truth, as both methods see it."""

    name: str
    xyz: np.ndarray          # (N, 3) float32
    instance: np.ndarray     # (N,) int64
    part_radius: float | None
    shape: tuple[int, ...]   # leading shape of `points`: (H, W) organized or (N,)

    @property
    def visible_threshold(self) -> int:
        """300 points at 640x480, scaled with the resolution; 300 for unorganized clouds."""
        return visible_threshold(self.shape[0] * self.shape[1]) if len(self.shape) == 2 \
            else VISIBLE_MIN_POINTS


def load_scene(path: Path, columns: str | None = None) -> Scene:
    """Read a scene NPZ (``points``, ``instance``, ``part_radius``; other keys ignored), or a
    labelled text scene (``columns``: "paper" ``x y z center_score instance``, the default, or
    "peer" ``x y z instance center_score``; no part radius: the caller fixes one)."""
    path = Path(path)
    if path.suffix.lower() == ".txt":
        return _load_text_scene(path, columns or "paper")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k in ("points", "instance", "part_radius")}
    except Exception as exc:  # noqa: BLE001 - zipfile/numpy raise many types for a bad file
        raise SceneError(f"scene {path}: cannot read as NPZ ({exc})") from exc
    for key, what in (("points", "float32 (H,W,3) or (N,3) in metres"),
                      ("instance", "int32 labels with the leading shape of 'points', 0 = none")):
        if key not in arrays:
            raise SceneError(f"scene {path}: missing key {key!r} ({what}); see DESIGN.md §4")
    points, instance = arrays["points"], arrays["instance"]
    if points.ndim not in (2, 3) or points.shape[-1] != 3:
        raise SceneError(f"scene {path}: 'points' has shape {points.shape}; expected (N,3) or "
                         "(H,W,3)")
    if instance.shape != points.shape[:-1]:
        raise SceneError(f"scene {path}: 'instance' has shape {instance.shape} but 'points' has "
                         f"{points.shape}; they must share the leading shape")
    radius = None
    if "part_radius" in arrays:
        radius = float(np.asarray(arrays["part_radius"]).reshape(-1)[0])
    return Scene(name=path.name, xyz=points.reshape(-1, 3).astype(np.float32, copy=False),
                 instance=instance.reshape(-1).astype(np.int64), part_radius=radius,
                 shape=tuple(points.shape[:-1]))


def _load_text_scene(path: Path, columns: str) -> Scene:
    from msg_tools.formats import FormatError, read_txt

    try:
        xyz, extra = read_txt(path, columns=columns)
    except (FormatError, OSError) as exc:
        raise SceneError(f"scene {path}: {exc}") from exc
    if "instance" not in extra:
        raise SceneError(f"scene {path}: no 'instance' column under columns={columns!r} (a text "
                         "scene needs x y z and the instance label; --columns paper is x y z "
                         "center_score instance, --columns peer is x y z instance center_score)")
    return Scene(name=path.name, xyz=xyz, instance=extra["instance"].astype(np.int64),
                 part_radius=None, shape=(len(xyz),))


def default_tolerances(part_radius: float) -> list[float]:
    """The baseline sweep for parts of this d_max, in metres (rounded to 0.1 mm)."""
    return sorted({round(float(f * part_radius), 4) for f in TOLERANCE_FRACTIONS} - {0.0})


@dataclass
class BaselineRun:
    """The baseline on one scene at one tolerance."""

    tolerance: float
    counts: dict[str, InstanceCounts]
    predicted: int
    ms: float                # plane removal (shared by the sweep) + clustering at this tolerance


@dataclass
class SceneResult:
    scene: str
    points: int
    valid_points: int
    part_radius: float
    visible_threshold: int
    gt_instances: int
    visible_gt: int
    predicted: int
    fpcc: dict[str, InstanceCounts]
    fpcc_ms: float
    fpcc_stages_ms: dict[str, float] = field(default_factory=dict)
    baseline: list[BaselineRun] = field(default_factory=list)

    def baseline_at(self, tolerance: float) -> BaselineRun | None:
        return next((run for run in self.baseline if run.tolerance == tolerance), None)


@dataclass
class EvalReport:
    scenes: list[SceneResult]
    protocols: tuple[str, ...]
    tolerances: list[float]
    skipped: list[tuple[str, str]] = field(default_factory=list)
    model: dict[str, Any] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    part_radius_source: str = "scene"

    # -- totals (counts summed over scenes, then ratios) -------------------------------------
    def fpcc_totals(self, protocol: str) -> InstanceCounts:
        return sum((s.fpcc[protocol] for s in self.scenes), InstanceCounts())

    def baseline_totals(self, protocol: str, tolerance: float) -> InstanceCounts:
        runs = (s.baseline_at(tolerance) for s in self.scenes)
        return sum((r.counts[protocol] for r in runs if r is not None), InstanceCounts())

    def best_tolerance(self, protocol: str) -> float | None:
        """The sweep's best tolerance by :data:`SELECTION_RULE`; None without a baseline."""
        best, best_f1 = None, -1.0
        for tol in self.tolerances:  # ascending, so ties keep the smaller tolerance
            f1 = f1_score(self.baseline_totals(protocol, tol))
            if f1 > best_f1:
                best, best_f1 = tol, f1
        return best

    # -- output --------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """The whole report as JSON-ready data (counts as well as ratios, so sets can be merged)."""
        best = {p: self.best_tolerance(p) for p in self.protocols}
        totals = {}
        for p in self.protocols:
            base = self.baseline_totals(p, best[p]) if best[p] is not None else None
            totals[p] = {"fpcc": _summary(self.fpcc_totals(p)),
                         "baseline": _summary(base) if base is not None else None}
        return {
            "format": REPORT_FORMAT,
            "model": self.model,
            "pipeline": {**self.config, "part_radius_source": self.part_radius_source},
            "protocols": list(self.protocols),
            "scenes_evaluated": len(self.scenes),
            "skipped": [{"scene": name, "reason": why} for name, why in self.skipped],
            "totals": totals,
            "baseline": {
                "method": "plane removal (floor + walls, fpcc_ros.baseline) then Euclidean "
                          "clustering (connected components of the radius graph)",
                "tolerances_m": list(self.tolerances),
                "best_tolerance_m": best,
                "selection": SELECTION_RULE,
                "plane_tolerance": "5% of part_radius, clipped to 2-10 mm",
                "min_points": self.config.get("min_points"),
                "by_tolerance": {p: [{"tolerance_m": t, **_summary(self.baseline_totals(p, t))}
                                     for t in self.tolerances] for p in self.protocols},
            },
            "timings_ms": {
                "fpcc": _stats([s.fpcc_ms for s in self.scenes]),
                "baseline_at_best": _stats([r.ms for s in self.scenes
                                            if (r := s.baseline_at(best[self.primary])) is not None]),
            },
            "scenes": [self._scene_json(s, best) for s in self.scenes],
        }

    @property
    def primary(self) -> str:
        """The protocol of the per-scene table: visible when evaluated (goals use it)."""
        return "visible" if "visible" in self.protocols else self.protocols[0]

    def table(self, protocol: str | None = None) -> str:
        """Per-scene text table for one protocol, with a totals row."""
        p = protocol or self.primary
        tol = self.best_tolerance(p)
        width = max([len(s.scene) for s in self.scenes] + [len("total"), 5])
        head = (f"{'scene':<{width}} {'GT':>4} {'visGT':>5} {'pred':>5} {'P':>6} {'R':>6} "
                f"{'MUCov':>6} {'MWCov':>6} | {'base P':>6} {'base R':>6} | {'fpcc ms':>8} "
                f"{'base ms':>8}")
        lines = [f"per scene, {p} protocol" + (f" (baseline at {_mm(tol)})" if tol else ""),
                 head, "-" * len(head)]

        def row(name, gt, vis, c, b, fms, bms) -> str:
            base = f"{b.precision:>6.3f} {b.recall:>6.3f}" if b is not None else f"{'-':>6} {'-':>6}"
            return (f"{name:<{width}} {gt:>4} {vis:>5} {c.predictions:>5} {c.precision:>6.3f} "
                    f"{c.recall:>6.3f} {c.mucov:>6.3f} {c.mwcov:>6.3f} | {base} | {fms:>8} {bms:>8}")

        for s in self.scenes:
            run = s.baseline_at(tol) if tol is not None else None
            lines.append(row(s.scene, s.gt_instances, s.visible_gt, s.fpcc[p],
                             run.counts[p] if run else None, f"{s.fpcc_ms:.0f}",
                             f"{run.ms:.0f}" if run else "-"))
        lines.append("-" * len(head))
        lines.append(row("total", sum(s.gt_instances for s in self.scenes),
                         sum(s.visible_gt for s in self.scenes), self.fpcc_totals(p),
                         self.baseline_totals(p, tol) if tol is not None else None,
                         f"{sum(s.fpcc_ms for s in self.scenes):.0f}",
                         f"{sum(r.ms for s in self.scenes if (r := s.baseline_at(tol))):.0f}"
                         if tol is not None else "-"))
        return "\n".join(lines)

    def summary(self) -> str:
        """FPCC and the baseline side by side for every protocol, totals over the set."""
        best = {p: self.best_tolerance(p) for p in self.protocols}
        cols = [(p, m) for p in self.protocols for m in ("FPCC", "baseline")]
        lines = [f"summary over {len(self.scenes)} scenes (counts summed, then ratios)",
                 f"{'':<14}" + "".join(f"{p:^22}" for p in self.protocols),
                 f"{'':<14}" + "".join(f"{m:>11}" for _, m in cols)]
        counts = {(p, m): (self.fpcc_totals(p) if m == "FPCC" else
                           self.baseline_totals(p, best[p]) if best[p] is not None else None)
                  for p, m in cols}
        for label, get in (("precision", lambda c: c.precision), ("recall", lambda c: c.recall),
                           ("F1", f1_score), ("MUCov", lambda c: c.mucov),
                           ("MWCov", lambda c: c.mwcov)):
            lines.append(f"{label:<14}" + "".join(
                f"{get(c):>11.3f}" if c is not None else f"{'-':>11}" for c in counts.values()))
        lines.append(f"{'TP/pred/GT':<14}" + "".join(
            f"{f'{c.true_positives}/{c.predictions}/{c.ground_truths}':>11}" if c is not None
            else f"{'-':>11}" for c in counts.values()))
        if self.tolerances:
            chosen = ", ".join(f"{p} {_mm(best[p])}" for p in self.protocols)
            lines.append(f"baseline: floor/wall removal + Euclidean clustering at its best "
                         f"tolerance: {chosen}")
            lines.append(f"  of {len(self.tolerances)} tried "
                         f"({', '.join(f'{t * 1e3:g}' for t in self.tolerances)} mm), chosen by "
                         f"{SELECTION_RULE}")
        else:
            lines.append("baseline: not run")
        fpcc_ms = _stats([s.fpcc_ms for s in self.scenes])["median"]
        timing = f"time per scene (median): FPCC {fpcc_ms:.0f} ms"
        if self.tolerances:
            base_ms = _stats([r.ms for s in self.scenes
                              if (r := s.baseline_at(best[self.primary]))])["median"]
            timing += f", baseline {base_ms:.0f} ms (plane removal + clustering at one tolerance)"
        lines.append(timing)
        source = "each scene's own" if self.part_radius_source == "scene" else "fixed by the user"
        lines.append(f"part_radius: {source}")
        if self.skipped:
            lines.append(f"skipped {len(self.skipped)} scene(s) without ground-truth instances: "
                         + ", ".join(name for name, _ in self.skipped))
        return "\n".join(lines)

    def _scene_json(self, s: SceneResult, best: dict[str, float | None]) -> dict[str, Any]:
        baseline = {}
        for p in self.protocols:
            run = s.baseline_at(best[p]) if best[p] is not None else None
            baseline[p] = {"tolerance_m": run.tolerance, "predicted": run.predicted, "ms": run.ms,
                           **_summary(run.counts[p])} if run else None
        return {
            "scene": s.scene, "points": s.points, "valid_points": s.valid_points,
            "part_radius": s.part_radius, "visible_threshold": s.visible_threshold,
            "gt_instances": s.gt_instances, "visible_gt": s.visible_gt, "predicted": s.predicted,
            "fpcc": {p: _summary(s.fpcc[p]) for p in self.protocols},
            "fpcc_ms": s.fpcc_ms, "fpcc_stages_ms": s.fpcc_stages_ms,
            "baseline": baseline,
            "baseline_sweep": [{"tolerance_m": r.tolerance, "predicted": r.predicted, "ms": r.ms,
                                **{p: asdict(r.counts[p]) for p in self.protocols}}
                               for r in s.baseline],
        }


def f1_score(counts: InstanceCounts) -> float:
    """2PR/(P+R) from counts: 2 TP / (predictions + ground truths)."""
    total = counts.predictions + counts.ground_truths
    return 2 * counts.true_positives / total if total else 0.0


def evaluate(scenes: Sequence[Path | str], pipeline, tolerances: Sequence[float] | None = None,
             protocols: Sequence[str] = PROTOCOLS, *, baseline: bool = True,
             fixed_part_radius: bool = False,
             progress: Callable[[Iterable], Iterable] | None = None,
             warn: Callable[[str], None] | None = None,
             columns: str | None = None) -> EvalReport:
    """Evaluate ``pipeline`` (anything with ``segment(xyz)`` and ``config``) and the baseline.

    Each scene runs at its own ``part_radius`` unless ``fixed_part_radius`` (the user set one).
    ``columns`` names the columns of .txt scenes (see :func:`load_scene`).
    ``tolerances`` None = :func:`default_tolerances` of the median part radius; ``baseline``
    False or an empty list skips the baseline. Scenes without any instance are skipped (listed
    in ``report.skipped`` and passed to ``warn``); :class:`EvalError` if none is left.
    """
    protocols = tuple(protocols)
    bad = [p for p in protocols if p not in PROTOCOLS]
    if bad or not protocols:
        raise EvalError(f"protocols={list(protocols)} is invalid; use any of {list(PROTOCOLS)}")
    paths = [Path(s) for s in scenes]
    if not paths:
        raise EvalError("no scenes to evaluate")
    radii = {path: _scene_radius(path, pipeline, fixed_part_radius) for path in paths}
    if not baseline:
        sweep: list[float] = []
    elif tolerances is None:
        sweep = default_tolerances(float(np.median(list(radii.values()))))
    else:
        sweep = sorted({float(t) for t in tolerances})
        if any(not math.isfinite(t) or t <= 0 for t in sweep):
            raise EvalError(f"baseline tolerances {sweep} must be positive lengths in metres")
    report = EvalReport(scenes=[], protocols=protocols, tolerances=sweep,
                        model=_model_info(pipeline), config=_config_info(pipeline.config),
                        part_radius_source="fixed" if fixed_part_radius else "scene")
    for path in (progress or (lambda it: it))(paths):
        scene = load_scene(path, columns)
        if not (scene.instance > 0).any():
            reason = "no ground-truth instances (every 'instance' label is 0)"
            report.skipped.append((scene.name, reason))
            if warn:
                warn(f"skipping {path}: {reason}")
            continue
        report.scenes.append(_evaluate_scene(scene, _with_part_radius(pipeline, radii[path], path),
                                             sweep, protocols))
    if not report.scenes:
        raise EvalError(f"none of the {len(paths)} scenes has ground-truth instances "
                        "('instance' > 0); nothing to evaluate")
    return report


def _evaluate_scene(scene: Scene, pipeline, sweep: list[float],
                    protocols: tuple[str, ...]) -> SceneResult:
    cfg = pipeline.config
    finite = np.isfinite(scene.xyz).all(axis=1)  # points with no return take part in no metric
    gt = scene.instance[finite]
    limit = scene.visible_threshold

    def counts(labels: np.ndarray) -> dict[str, InstanceCounts]:
        return {p: scene_counts(labels[finite], gt, p, min_visible=limit) for p in protocols}

    t0 = time.perf_counter()
    result = pipeline.segment(scene.xyz)
    fpcc_ms = (time.perf_counter() - t0) * 1e3

    runs = []
    if sweep:
        roi_min, roi_max = getattr(cfg, "roi_min", None), getattr(cfg, "roi_max", None)
        roi = (roi_min, roi_max) if roi_min is not None else None
        t0 = time.perf_counter()
        mask, _ = foreground_mask(scene.xyz, default_plane_tolerance(cfg.part_radius), roi)
        planes_ms = (time.perf_counter() - t0) * 1e3
        for tol in sweep:
            t0 = time.perf_counter()
            labels = cluster_foreground(scene.xyz, mask, tol, getattr(cfg, "min_points", 50))
            ms = planes_ms + (time.perf_counter() - t0) * 1e3
            runs.append(BaselineRun(tol, counts(labels), int(labels.max(initial=0)), ms))

    sizes = np.bincount(gt[gt > 0])
    return SceneResult(scene=scene.name, points=len(scene.xyz), valid_points=int(finite.sum()),
                       part_radius=float(cfg.part_radius), visible_threshold=limit,
                       gt_instances=int((sizes > 0).sum()), visible_gt=int((sizes >= limit).sum()),
                       predicted=int(len(np.unique(result.labels[result.labels > 0]))),
                       fpcc=counts(np.asarray(result.labels)), fpcc_ms=fpcc_ms,
                       fpcc_stages_ms=dict(getattr(result, "timings_ms", {}) or {}), baseline=runs)


def _scene_radius(path: Path, pipeline, fixed: bool) -> float:
    if fixed:
        return float(pipeline.config.part_radius)
    if not path.is_file():
        raise SceneError(f"scene {path} does not exist")
    if path.suffix.lower() == ".txt":
        raise SceneError(f"scene {path}: a text scene has no part radius; give the part's d_max "
                         "with --part-radius (`fpcc part-info MESH` prints it)")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "part_radius" not in z.files:
                raise SceneError(f"scene {path}: missing key 'part_radius' (the part's d_max in "
                                 "metres, DESIGN.md §4); add it or fix one with --part-radius")
            value = float(np.asarray(z["part_radius"]).reshape(-1)[0])
    except SceneError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise SceneError(f"scene {path}: cannot read as NPZ ({exc})") from exc
    if not math.isfinite(value) or value <= 0:
        raise SceneError(f"scene {path}: part_radius={value!r} must be a positive length in "
                         "metres; fix the file or pass --part-radius")
    return value


def _with_part_radius(pipeline, radius: float, path: Path):
    """The pipeline at this scene's part radius (a shallow copy sharing the model)."""
    if pipeline.config.part_radius == radius:
        return pipeline
    clone = copy.copy(pipeline)
    try:
        clone.config = pipeline.config.replace(part_radius=radius)
    except ValueError as exc:
        raise SceneError(f"scene {path}: {exc}") from exc
    return clone


def _model_info(pipeline) -> dict[str, Any]:
    model = getattr(pipeline, "model", None)
    card = getattr(model, "card", None)
    info: dict[str, Any] = {}
    if model is not None and getattr(model, "path", None) is not None:
        info["path"] = str(model.path)
    if card is not None:
        info.update(name=card.name, description=card.description, trained_on=card.trained_on)
    return info


def _config_info(config) -> dict[str, Any]:
    if is_dataclass(config):
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()}
    return {"part_radius": getattr(config, "part_radius", None),
            "min_points": getattr(config, "min_points", None)}


def _summary(counts: InstanceCounts) -> dict[str, Any]:
    return {**counts.summary(), "f1": f1_score(counts), "cov_sum": counts.cov_sum,
            "weighted_cov_sum": counts.weighted_cov_sum, "gt_points": counts.gt_points}


def _stats(values: list[float]) -> dict[str, float]:
    if not values:
        return {"mean": 0.0, "median": 0.0, "max": 0.0}
    return {"mean": float(np.mean(values)), "median": float(np.median(values)),
            "max": float(np.max(values))}


def _mm(tolerance: float | None) -> str:
    return "-" if tolerance is None else f"{tolerance * 1e3:g} mm"
