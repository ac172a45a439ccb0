"""FPCC against the classical baselines on labelled scenes (DESIGN.md §4b).

For every scene NPZ all methods segment the SAME points; counts are taken under the ``paper``
and ``visible`` protocols (fpcc_ros.metrics) and summed over the set before any ratio is formed.
The baselines (crop + floor/wall removal, then Euclidean clustering or DBSCAN, small clusters
dropped) are tuned as a careful user would tune them (fpcc_ros.baseline_sweep): every setting
of a grid on the first few scenes of each part, the best one per protocol then run on every
scene of that part. FPCC is reported against the stronger of the two on the whole set, so it is
never compared against a strawman, nor against one tuned for another part. Timings are per
scene, wall clock.
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from fpcc_ros.baseline import default_plane_tolerance, foreground_mask
from fpcc_ros.baseline_sweep import (DEFAULT_TUNE_SCENES, METHOD_NAMES, METHODS, SELECTION_RULE,
                                     MIN_CLUSTER_SIZES, MIN_SAMPLES, Grid, Setting, choose,
                                     default_distances, sweep_scene)
from fpcc_ros.metrics import (VISIBLE_MIN_POINTS, InstanceCounts, f1_score, scene_counts,
                              visible_threshold)
from fpcc_ros.miss_causes import add_causes, describe, error_causes

PROTOCOLS = ("paper", "visible")
REPORT_FORMAT = "fpcc_ros/eval-report/3"  # 2: two tuned baselines (issue 24); 3: tuned per part


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


@dataclass
class BaselineRun:
    """A baseline on one scene at one (chosen) setting."""

    setting: Setting
    counts: dict[str, InstanceCounts]
    predicted: int
    ms: float                # crop + plane removal + clustering at this setting
    planes_ms: float = 0.0   # the crop + plane removal part of ms


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
    causes: dict[str, dict[str, int]] | None = None   # fpcc_ros.miss_causes (visible protocol)
    part: str = ""           # the baselines' tuning group (:func:`part_of`)

    def baseline_at(self, setting: Setting | None) -> BaselineRun | None:
        return next((run for run in self.baseline if run.setting == setting), None)


@dataclass
class PartTuning:
    """The baselines as tuned for one part: a user tunes DBSCAN for each part, on scenes of that
    part, with link distances scaled to its size."""

    grid: Grid
    scenes: list[str] = field(default_factory=list)   # the tuning scenes
    # every grid setting's counts summed over the tuning scenes, and the choice per method/protocol
    totals: dict[Setting, dict[str, InstanceCounts]] = field(default_factory=dict)
    chosen: dict[str, dict[str, Setting]] = field(default_factory=dict)


@dataclass
class EvalReport:
    scenes: list[SceneResult]
    protocols: tuple[str, ...]
    tunings: dict[str, PartTuning] = field(default_factory=dict)   # empty: no baseline
    skipped: list[tuple[str, str]] = field(default_factory=list)
    model: dict[str, Any] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    part_radius_source: str = "scene"

    @property
    def tune_scenes(self) -> list[str]:
        """Every part's tuning scenes."""
        return [name for tuning in self.tunings.values() for name in tuning.scenes]

    # -- totals (counts summed over scenes, then ratios) -------------------------------------
    def fpcc_totals(self, protocol: str) -> InstanceCounts:
        return sum((s.fpcc[protocol] for s in self.scenes), InstanceCounts())

    def error_causes(self) -> dict[str, dict[str, int]] | None:
        """Missed parts and extra instances by cause, summed over the scenes (visible only)."""
        total = None
        for s in self.scenes:
            if s.causes is not None:
                total = add_causes(total, s.causes)
        return total

    def baseline_setting(self, method: str, protocol: str, part: str | None = None
                         ) -> Setting | None:
        """The setting tuned for ``method`` under ``protocol`` on ``part`` (None: the only
        part's; None without a baseline, or with several parts and no ``part``)."""
        if part is None and len(self.tunings) == 1:
            part = next(iter(self.tunings))
        tuning = self.tunings.get(part) if part is not None else None
        return tuning.chosen.get(method, {}).get(protocol) if tuning else None

    def baseline_runs(self, method: str, protocol: str, part: str | None = None
                      ) -> list[BaselineRun]:
        """``method`` on every scene (of ``part``, if given) at its part's tuned setting."""
        return [r for s in self.scenes if part is None or s.part == part
                if (r := s.baseline_at(self.baseline_setting(method, protocol, s.part)))]

    def baseline_totals(self, protocol: str, method: str | None = None) -> InstanceCounts | None:
        """A baseline's counts over every scene at its part's tuned setting; ``method`` None =
        the stronger one (:meth:`stronger_baseline`)."""
        method = method or self.stronger_baseline(protocol)
        if method is None or not self.tunings:
            return None
        return sum((r.counts[protocol] for r in self.baseline_runs(method, protocol)),
                   InstanceCounts())

    def stronger_baseline(self, protocol: str) -> str | None:
        """The method whose tuned settings score the higher F1 on the whole set (what FPCC is
        compared with; a tie goes to Euclidean clustering, the simpler)."""
        best, best_f1 = None, -1.0
        for method in METHODS if self.tunings else ():
            f1 = f1_score(self.baseline_totals(protocol, method))
            if f1 > best_f1:
                best, best_f1 = method, f1
        return best

    def baseline_ms(self, method: str, protocol: str | None = None) -> list[float]:
        """Time per scene of ``method`` at its part's tuned setting (crop + planes + clustering)."""
        return [r.ms for r in self.baseline_runs(method, protocol or self.primary)]

    # -- output --------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """The whole report as JSON-ready data (counts as well as ratios, so sets can be merged)."""
        totals = {}
        for p in self.protocols:
            totals[p] = {"fpcc": _summary(self.fpcc_totals(p)),
                         "baseline": _maybe_summary(self.baseline_totals(p)),
                         **{m: _maybe_summary(self.baseline_totals(p, m)) for m in METHODS}}
        return {
            "format": REPORT_FORMAT,
            "model": self.model,
            "pipeline": {**self.config, "part_radius_source": self.part_radius_source},
            "protocols": list(self.protocols),
            "scenes_evaluated": len(self.scenes),
            "skipped": [{"scene": name, "reason": why} for name, why in self.skipped],
            "totals": totals,
            "error_causes": self.error_causes(),
            "baseline": self._baseline_json(),
            "timings_ms": {"fpcc": _stats([s.fpcc_ms for s in self.scenes]),
                           **{m: _stats(self.baseline_ms(m)) for m in METHODS
                              if self.tunings}},
            "scenes": [self._scene_json(s) for s in self.scenes],
        }

    def _baseline_json(self) -> dict[str, Any] | None:
        if not self.tunings:
            return None
        return {
            "stronger": {p: self.stronger_baseline(p) for p in self.protocols},
            "method": "crop (the pipeline's roi_min/roi_max, if set), floor and wall removal "
                      "(fpcc_ros.baseline), then Euclidean clustering or DBSCAN, clusters under "
                      "a minimum size dropped; tuned per part",
            "plane_tolerance": "5% of part_radius, clipped to 2-10 mm",
            "selection": SELECTION_RULE,
            "parts": {part: self._tuning_json(t) for part, t in self.tunings.items()},
        }

    def _tuning_json(self, tuning: PartTuning) -> dict[str, Any]:
        methods = {}
        for m in METHODS:
            chosen = {p: tuning.chosen[m][p] for p in self.protocols}
            ranked = {p: sorted((s for s in tuning.totals if s.method == m),
                                key=lambda s: -f1_score(tuning.totals[s][p]))[:10]
                      for p in self.protocols}
            methods[m] = {
                "name": METHOD_NAMES[m],
                "setting": {p: chosen[p].to_json() for p in self.protocols},
                "tuning_totals": {p: _summary(tuning.totals[chosen[p]][p]) for p in self.protocols},
                "top_tuning_settings": {p: [{**s.to_json(), **_summary(tuning.totals[s][p])}
                                            for s in ranked[p]] for p in self.protocols},
            }
        return {"tune_scenes": list(tuning.scenes), "grid": tuning.grid.to_json(),
                "methods": methods}

    @property
    def primary(self) -> str:
        """The protocol of the per-scene table: visible when evaluated (goals use it)."""
        return "visible" if "visible" in self.protocols else self.protocols[0]

    def table(self, protocol: str | None = None) -> str:
        """Per-scene text table for one protocol, FPCC beside the stronger baseline, totals row."""
        p = protocol or self.primary
        method = self.stronger_baseline(p)
        setting = self.baseline_setting(method, p) if method else None
        width = max([len(s.scene) for s in self.scenes] + [len("total"), 5])
        head = (f"{'scene':<{width}} {'GT':>4} {'visGT':>5} {'pred':>5} {'P':>6} {'R':>6} "
                f"{'MUCov':>6} {'MWCov':>6} | {'base P':>6} {'base R':>6} | {'fpcc ms':>8} "
                f"{'base ms':>8}")
        title = f"per scene, {p} protocol"
        if setting is not None:
            title += f" (baseline: {setting.describe()})"
        elif method is not None:
            title += f" (baseline: {METHOD_NAMES[method]}, each part at its own tuned setting)"
        lines = [title, head, "-" * len(head)]

        def row(name, gt, vis, c, b, fms, bms) -> str:
            base = f"{b.precision:>6.3f} {b.recall:>6.3f}" if b is not None else f"{'-':>6} {'-':>6}"
            return (f"{name:<{width}} {gt:>4} {vis:>5} {c.predictions:>5} {c.precision:>6.3f} "
                    f"{c.recall:>6.3f} {c.mucov:>6.3f} {c.mwcov:>6.3f} | {base} | {fms:>8} {bms:>8}")

        for s in self.scenes:
            run = s.baseline_at(self.baseline_setting(method, p, s.part)) if method else None
            mark = "*" if s.scene in self.tune_scenes else ""
            lines.append(row(s.scene + mark, s.gt_instances, s.visible_gt, s.fpcc[p],
                             run.counts[p] if run else None, f"{s.fpcc_ms:.0f}",
                             f"{run.ms:.0f}" if run else "-"))
        lines.append("-" * len(head))
        lines.append(row("total", sum(s.gt_instances for s in self.scenes),
                         sum(s.visible_gt for s in self.scenes), self.fpcc_totals(p),
                         self.baseline_totals(p),
                         f"{sum(s.fpcc_ms for s in self.scenes):.0f}",
                         f"{sum(self.baseline_ms(method, p)):.0f}" if method else "-"))
        if self.tune_scenes:
            lines.append("* tuning scene of the baselines")
        return "\n".join(lines)

    def summary(self) -> str:
        """FPCC and the stronger baseline side by side for every protocol, totals over the set."""
        cols = [(p, m) for p in self.protocols for m in ("FPCC", "baseline")]
        lines = [f"summary over {len(self.scenes)} scenes (counts summed, then ratios)",
                 f"{'':<14}" + "".join(f"{p:^22}" for p in self.protocols),
                 f"{'':<14}" + "".join(f"{m:>11}" for _, m in cols)]
        counts = {(p, m): self.fpcc_totals(p) if m == "FPCC" else self.baseline_totals(p)
                  for p, m in cols}
        for label, get in (("precision", lambda c: c.precision), ("recall", lambda c: c.recall),
                           ("F1", f1_score), ("MUCov", lambda c: c.mucov),
                           ("MWCov", lambda c: c.mwcov)):
            lines.append(f"{label:<14}" + "".join(
                f"{get(c):>11.3f}" if c is not None else f"{'-':>11}" for c in counts.values()))
        lines.append(f"{'TP/pred/GT':<14}" + "".join(
            f" {f'{c.true_positives}/{c.predictions}/{c.ground_truths}':>10}" if c is not None
            else f"{'-':>11}" for c in counts.values()))
        causes = self.error_causes()
        if causes is not None:
            lines.extend(f"FPCC {line}" for line in describe(causes))
        lines.extend(self._baseline_lines())
        fpcc_ms = _stats([s.fpcc_ms for s in self.scenes])["median"]
        lines.append(f"time per scene (median): FPCC {fpcc_ms:.0f} ms")
        source = "each scene's own" if self.part_radius_source == "scene" else "fixed by the user"
        lines.append(f"part_radius: {source}")
        if self.skipped:
            lines.append(f"skipped {len(self.skipped)} scene(s) without ground-truth instances: "
                         + ", ".join(name for name, _ in self.skipped))
        return "\n".join(lines)

    def _baseline_lines(self) -> list[str]:
        """Which baseline is the stronger, the tuned settings with their scores and times."""
        if not self.tunings:
            return ["baseline: not run"]
        several = len(self.tunings) > 1
        methods = " or ".join(METHOD_NAMES[m] for m in METHODS)
        if several:
            lines = [f"baseline = the stronger on this set of: crop + floor/wall removal, then "
                     f"{methods}, each tuned per part ({len(self.tunings)} parts) on that "
                     "part's first scenes:"]
            lines.extend(f"  {_part_label(part)}: tuned on {len(t.scenes)} scene(s) "
                         f"({', '.join(t.scenes)})" for part, t in self.tunings.items())
        else:
            lines = [f"baseline = the stronger on this set of: crop + floor/wall removal, then "
                     f"{methods}, each tuned on {len(self.tune_scenes)} scene(s) "
                     f"({', '.join(self.tune_scenes)})"]
        for p in self.protocols:
            stronger = self.stronger_baseline(p)
            for m in METHODS:
                c = self.baseline_totals(p, m)
                runs = self.baseline_runs(m, p)
                ms = _stats([r.ms for r in runs])["median"]
                planes = _stats([r.planes_ms for r in runs])["median"]
                name = METHOD_NAMES[m] if several else self.baseline_setting(m, p).describe()
                lines.append(f"  {p:<8}{'*' if m == stronger else ' '} {name}: "
                             f"P {c.precision:.3f} R {c.recall:.3f} F1 {f1_score(c):.3f}, "
                             f"{ms:.0f} ms per scene (median; crop + planes {planes:.0f})")
                if several:
                    lines.extend(self._part_line(part, t.chosen[m][p], p)
                                 for part, t in self.tunings.items())
        for part, t in self.tunings.items():
            g = t.grid
            lines.append(f"  grid{f' ({_part_label(part)})' if several else ''}: distance "
                         f"{', '.join(f'{d * 1e3:g}' for d in g.distances)} mm; min_samples "
                         f"{', '.join(map(str, g.min_samples))}; min cluster "
                         f"{', '.join(map(str, g.min_cluster_sizes))} points")
        lines.append(f"  selection: {SELECTION_RULE}")
        return lines

    def _part_line(self, part: str, setting: Setting, protocol: str) -> str:
        """One part's setting with its own figures and FPCC's on the same scenes."""
        base = sum((r.counts[protocol] for r in self.baseline_runs(setting.method, protocol, part)),
                   InstanceCounts())
        fpcc = sum((s.fpcc[protocol] for s in self.scenes if s.part == part), InstanceCounts())
        return (f"{'':14}{_part_label(part)}: {setting.describe()}: P {base.precision:.3f} "
                f"R {base.recall:.3f} F1 {f1_score(base):.3f} (FPCC F1 {f1_score(fpcc):.3f})")

    def _scene_json(self, s: SceneResult) -> dict[str, Any]:
        baseline: dict[str, Any] = {}
        for m in METHODS:
            for p in self.protocols:
                run = s.baseline_at(self.baseline_setting(m, p, s.part))
                baseline.setdefault(m, {})[p] = {
                    **run.setting.to_json(), "predicted": run.predicted, "ms": run.ms,
                    "planes_ms": run.planes_ms,
                    **_summary(run.counts[p])} if run else None
        return {
            "scene": s.scene, "part": s.part, "points": s.points, "valid_points": s.valid_points,
            "part_radius": s.part_radius, "visible_threshold": s.visible_threshold,
            "gt_instances": s.gt_instances, "visible_gt": s.visible_gt, "predicted": s.predicted,
            "fpcc": {p: _summary(s.fpcc[p]) for p in self.protocols},
            "fpcc_ms": s.fpcc_ms, "fpcc_stages_ms": s.fpcc_stages_ms,
            "error_causes": s.causes,
            "tuning_scene": s.scene in self.tune_scenes,
            "baseline": baseline,
        }


def evaluate(scenes: Sequence[Path | str], pipeline, tolerances: Sequence[float] | None = None,
             protocols: Sequence[str] = PROTOCOLS, *, baseline: bool = True,
             min_samples: Sequence[int] = MIN_SAMPLES,
             min_cluster_sizes: Sequence[int] = MIN_CLUSTER_SIZES,
             tune_scenes: int = DEFAULT_TUNE_SCENES,
             fixed_part_radius: bool = False,
             progress: Callable[[Iterable], Iterable] | None = None,
             warn: Callable[[str], None] | None = None,
             columns: str | None = None, oracle: tuple[str, ...] = (),
             root: Path | None = None) -> EvalReport:
    """Evaluate ``pipeline`` (anything with ``segment(xyz, image_shape)`` and ``config``) and
    the baselines.

    ``oracle``: the network outputs (fpcc_ros.oracle.ORACLE_HEADS) each scene's ground truth
    stands in for: both, and the FPCC figures are the ceiling of the pipeline's clustering on
    these scenes; one, and they say how far a perfect head of that kind would take the model.

    Each scene runs at its own ``part_radius`` unless ``fixed_part_radius`` (the user set one).
    ``columns`` names the columns of .txt scenes (see :func:`load_scene`). ``root``: scenes are
    named by their path below it (``part_a/scene_00000.npz``), else by their file name.
    The baselines are tuned per part (:func:`part_of`) on its first ``tune_scenes`` evaluated
    scenes over ``tolerances`` (link distances, metres; None = :func:`default_distances` of the
    part's median part radius) x ``min_samples`` (DBSCAN) x ``min_cluster_sizes``, then run at
    the chosen settings on every scene of that part; ``baseline`` False or an empty
    ``tolerances`` skips them. Scenes without any instance
    are skipped (listed in ``report.skipped`` and passed to ``warn``); :class:`EvalError` if
    none is left.
    """
    protocols = tuple(protocols)
    bad = [p for p in protocols if p not in PROTOCOLS]
    if bad or not protocols:
        raise EvalError(f"protocols={list(protocols)} is invalid; use any of {list(PROTOCOLS)}")
    paths = [Path(s) for s in scenes]
    if not paths:
        raise EvalError("no scenes to evaluate")
    if tune_scenes < 1:
        raise EvalError(f"baseline tuning scenes {tune_scenes} must be at least 1")
    radii = {path: _scene_radius(path, pipeline, fixed_part_radius) for path in paths}
    parts = {path: part_of(path, root) for path in paths}
    report = EvalReport(scenes=[], protocols=protocols,
                        model=_model_info(pipeline), config=_config_info(pipeline.config),
                        part_radius_source="fixed" if fixed_part_radius else "scene")
    tuners: dict[str, _Tuner] = {}
    if baseline and (tolerances is None or len(tolerances)):
        for part in dict.fromkeys(parts.values()):
            part_radii = [radii[path] for path in paths if parts[path] == part]
            distances = default_distances(float(np.median(part_radii))) \
                if tolerances is None else tolerances
            try:
                grid = Grid(tuple(distances), tuple(min_samples), tuple(min_cluster_sizes))
            except ValueError as exc:
                raise EvalError(str(exc)) from exc
            report.tunings[part] = PartTuning(grid)
            tuners[part] = _Tuner(report.tunings[part], tune_scenes, protocols)
    if oracle:
        from fpcc_ros.oracle import ORACLE_HEADS, oracle_for_scene
        report.model["oracle"] = "ground truth in place of the network" \
            if set(oracle) == set(ORACLE_HEADS) else \
            f"ground truth in place of the network's {' and '.join(oracle)}"
    for path in (progress or (lambda it: it))(paths):
        scene = load_scene(path, columns)
        if root is not None:   # sub-folders of one --data hold files of the same name
            scene.name = path.relative_to(root).as_posix()
        if not (scene.instance > 0).any():
            reason = "no ground-truth instances (every 'instance' label is 0)"
            report.skipped.append((scene.name, reason))
            if warn:
                warn(f"skipping {path}: {reason}")
            continue
        scene_pipeline = _with_part_radius(pipeline, radii[path], path)
        result = _evaluate_scene(
            scene, oracle_for_scene(scene_pipeline, path, oracle) if oracle else scene_pipeline,
            protocols)
        result.part = parts[path]
        report.scenes.append(result)
        if tuners:
            tuners[result.part].add(result, _BaselineInput.of(scene, scene_pipeline.config,
                                                              protocols))
    if not report.scenes:
        raise EvalError(f"none of the {len(paths)} scenes has ground-truth instances "
                        "('instance' > 0); nothing to evaluate")
    for part, tuner in tuners.items():
        if tuner.tuning.scenes:
            tuner.finish()
        else:   # every scene of this part was skipped
            del report.tunings[part]
    return report


def part_of(path: Path, root: Path | None = None) -> str:
    """Which part a scene shows, for tuning the baselines: its ``part_name`` (scenes of
    `fpcc synth`), else its folder below ``root`` ("" for scenes directly in it)."""
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                if "part_name" in z.files:
                    return str(np.asarray(z["part_name"]))
        except Exception:  # noqa: BLE001 - load_scene reports an unreadable file
            pass
    if root is not None and path.is_relative_to(root):
        folder = path.parent.relative_to(root).as_posix()
        return "" if folder == "." else folder
    return ""


def _part_label(part: str) -> str:
    return part or "(no part name)"


def _evaluate_scene(scene: Scene, pipeline, protocols: tuple[str, ...]) -> SceneResult:
    cfg = pipeline.config
    finite = np.isfinite(scene.xyz).all(axis=1)  # points with no return take part in no metric
    gt = scene.instance[finite]
    limit = scene.visible_threshold

    t0 = time.perf_counter()
    result = pipeline.segment(scene.xyz, scene.shape if len(scene.shape) == 2 else None)
    fpcc_ms = (time.perf_counter() - t0) * 1e3

    labels = np.asarray(result.labels)[finite]
    sizes = np.bincount(gt[gt > 0])
    causes = None
    if "visible" in protocols:
        centers = getattr(result, "center_points", None)
        finite_index = np.cumsum(finite) - 1      # input point -> its row among finite points
        causes = error_causes(labels.astype(np.int64), gt, np.asarray(result.center_score)[finite],
                              None if centers is None else finite_index[centers],
                              cfg.score_threshold, limit)
    return SceneResult(scene=scene.name, points=len(scene.xyz), valid_points=int(finite.sum()),
                       part_radius=float(cfg.part_radius), visible_threshold=limit,
                       gt_instances=int((sizes > 0).sum()), visible_gt=int((sizes >= limit).sum()),
                       predicted=int(len(np.unique(result.labels[result.labels > 0]))),
                       fpcc={p: scene_counts(labels, gt, p, min_visible=limit) for p in protocols},
                       fpcc_ms=fpcc_ms,
                       fpcc_stages_ms=dict(getattr(result, "timings_ms", {}) or {}),
                       causes=causes)


@dataclass
class _BaselineInput:
    """What the baselines need of one scene: its points, the crop + plane removal mask (computed
    once, timed once: it is part of every setting's time) and the ground truth it is scored on."""

    xyz: np.ndarray          # (N, 3) float64
    foreground: np.ndarray   # (N,) bool
    planes_ms: float
    finite: np.ndarray
    gt: np.ndarray           # ground truth of the finite points
    limit: int
    protocols: tuple[str, ...]

    @classmethod
    def of(cls, scene: Scene, cfg, protocols: tuple[str, ...]) -> "_BaselineInput":
        xyz = scene.xyz.astype(np.float64)
        roi_min, roi_max = getattr(cfg, "roi_min", None), getattr(cfg, "roi_max", None)
        roi = (roi_min, roi_max) if roi_min is not None else None
        t0 = time.perf_counter()
        mask, _ = foreground_mask(xyz, default_plane_tolerance(cfg.part_radius), roi)
        planes_ms = (time.perf_counter() - t0) * 1e3
        finite = np.isfinite(xyz).all(axis=1)
        return cls(xyz, mask, planes_ms, finite, scene.instance[finite], scene.visible_threshold,
                   protocols)

    def run(self, setting: Setting) -> BaselineRun:
        t0 = time.perf_counter()
        labels = setting.run(self.xyz, self.foreground)
        ms = self.planes_ms + (time.perf_counter() - t0) * 1e3
        counts = {p: scene_counts(labels[self.finite], self.gt, p, min_visible=self.limit)
                  for p in self.protocols}
        return BaselineRun(setting, counts, int(len(np.unique(labels[labels > 0]))), ms,
                           self.planes_ms)


class _Tuner:
    """Sweeps one part's grid on its first ``count`` scenes, then runs the chosen settings on
    all of that part's scenes."""

    def __init__(self, tuning: PartTuning, count: int, protocols: tuple[str, ...]):
        self.tuning, self.count, self.protocols = tuning, count, protocols
        self.pending: list[tuple[SceneResult, _BaselineInput]] = []

    def add(self, result: SceneResult, data: _BaselineInput) -> None:
        tuning = self.tuning
        if tuning.chosen:
            self._run_chosen(result, data)
            return
        counts = sweep_scene(data.xyz, data.foreground, data.gt, data.finite, data.protocols,
                             data.limit, tuning.grid)
        for setting, by_protocol in counts.items():
            total = tuning.totals.setdefault(setting, {p: InstanceCounts()
                                                       for p in data.protocols})
            for p, c in by_protocol.items():
                total[p] = total[p] + c
        tuning.scenes.append(result.scene)
        self.pending.append((result, data))
        if len(self.pending) >= self.count:
            self.finish()

    def finish(self) -> None:
        """Choose (if not yet) and run the choice on the tuning scenes held back."""
        tuning = self.tuning
        if not tuning.chosen:
            for method in METHODS:
                tuning.chosen[method] = {p: choose(tuning.totals, method, p)
                                         for p in self.protocols}
        for result, data in self.pending:
            self._run_chosen(result, data)
        self.pending.clear()

    def _run_chosen(self, result: SceneResult, data: _BaselineInput) -> None:
        settings = sorted({s for by_p in self.tuning.chosen.values() for s in by_p.values()})
        result.baseline.extend(data.run(s) for s in settings)


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


def _maybe_summary(counts: InstanceCounts | None) -> dict[str, Any] | None:
    return None if counts is None else _summary(counts)


def _stats(values: list[float]) -> dict[str, float]:
    if not values:
        return {"mean": 0.0, "median": 0.0, "max": 0.0}
    return {"mean": float(np.mean(values)), "median": float(np.median(values)),
            "max": float(np.max(values))}
