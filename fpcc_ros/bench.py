"""Latency benchmark of the whole per-frame path, with the accuracy of the same runs.

What is timed is exactly what the node does with a frame (:func:`fpcc_ros.frame.process_cloud`):
PointCloud2 bytes -> decode -> crop -> voxel downsample -> floor -> blocks, features, kNN ->
ONNX -> NMS -> clustering -> labels to every point -> PointCloud2 / PoseArray / markers. Each
scene gets one untimed warm-up run, then ``runs`` timed ones; per stage we report the median and
the 90th percentile. Precision and recall (IoU 0.5, visible protocol) are computed from the
labels of the same runs, so a speed-up that costs accuracy shows in the same table.

Scenes (all 640x480 organized, as a depth camera publishes them):

* ``demo``: the frames of ``bags/demo``. Their ground truth is regenerated from the seeds in
  ``bags/demo.json`` when the regenerated points match the bag's (else precision/recall "n/a").
* ``synth``: bins of ``part`` with 5..40 copies from :mod:`fpcc_ros.training.synth`, generated
  once into a cache directory (deterministic seeds), plus central crops of one of them so that
  latency can be plotted against the number of valid points.

Scene generation needs the training dependencies (pybullet) the first time only; everything
timed is runtime code.
"""
from __future__ import annotations

import json
import math
import os
import platform
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from fpcc_ros.metrics import VISIBLE_MIN_POINTS, InstanceCounts, scene_counts, visible_threshold

REPORT_FORMAT = "fpcc_ros/bench-report/1"
REPO = Path(__file__).resolve().parent.parent
DEMO_BAG = REPO / "bags" / "demo"
DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "fpcc_bench"
DEFAULT_PART = "gear_shaft"
DEFAULT_PART_SEED = 42        # the demo bag's part (held-out dimensions of the built-in part)
DEFAULT_PARTS = (5, 10, 20, 30, 40)
SYNTH_SEED = 7100             # scene seed = SYNTH_SEED + number of parts
DEFAULT_CROPS = (0.25, 0.5)   # fractions of the image area (central windows) of the crop scene
CROP_PARTS = 20               # the synth scene the crops are cut from
CLUTTER_PARTS = (20, 30)      # "cluttered bin" in the goals
# Stage names in pipeline order (fpcc_ros.pipeline and fpcc_ros.frame); "total" is end to end.
STAGES = ("decode", "valid", "downsample", "floor", "features", "inference", "nms", "cluster",
          "fragments", "labels", "encode", "total")   # fragments: the connected clustering's
CAMERA_FIELDS = (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7))  # FLOAT32


# ---------------------------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------------------------
@dataclass
class BenchScene:
    """One benchmark input: a PointCloud2 as the node receives it plus its ground truth."""

    name: str
    kind: str                      # "demo" | "synth" | "crop"
    msg: Any                       # PointCloud2 (rclpy flavour when available)
    part_radius: float
    gt: np.ndarray | None          # (H*W,) instance labels, 0 = none; None = no ground truth
    gt_note: str = ""              # why there is no ground truth
    num_parts: int | None = None   # copies of the part in the tote (ground truth)
    min_visible: int = VISIBLE_MIN_POINTS
    center_score: np.ndarray | None = None  # (H*W,) ground-truth center scores (synth only)

    @property
    def num_points(self) -> int:
        return int(self.msg.height) * int(self.msg.width)


def _message_types():
    """rclpy messages (what the node receives) when rclpy is importable, else rosbags ones."""
    try:
        from msg_tools.msg_types import RCLPY
        RCLPY.cls("sensor_msgs/msg/PointCloud2")
        return RCLPY
    except Exception:  # noqa: BLE001 - no ROS 2 Python packages: the rosbags flavour still works
        from msg_tools.msg_types import ROSBAGS
        return ROSBAGS


def camera_cloud(xyz: np.ndarray, types: Any, frame_id: str = "camera_depth_optical_frame",
                 stamp_ns: int = 0) -> Any:
    """An organized (H, W, 3) cloud as a camera driver publishes it: x, y, z, intensity FLOAT32."""
    from msg_tools.point_cloud2 import Field, create_cloud

    xyz = np.asarray(xyz, np.float32)
    intensity = np.where(np.isfinite(xyz[..., 2]), 1.0 / np.maximum(xyz[..., 2], 0.1), np.nan)
    points = np.concatenate([xyz, intensity[..., None].astype(np.float32)], axis=-1)
    header = types.header(frame_id, stamp_ns // 10**9, stamp_ns % 10**9)
    return create_cloud(header, [Field(*f) for f in CAMERA_FIELDS], points, types=types)


def synth_scene_path(cache: Path, part: str, part_seed: int, num_parts: int) -> Path:
    return Path(cache) / f"{part}_p{part_seed}_n{num_parts}_s{SYNTH_SEED + num_parts}.npz"


def load_or_generate(path: Path, generate: Callable[[], dict]) -> dict[str, np.ndarray]:
    """The scene NPZ at ``path``, generated (and written atomically) on the first call."""
    if not path.is_file():
        scene = generate()
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.stem + f".tmp{os.getpid()}.npz")
        np.savez_compressed(tmp, **{k: scene[k] for k in
                                    ("points", "instance", "center_score", "part_radius",
                                                "num_parts")})
        os.replace(tmp, path)
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def synth_scenes(parts_counts: Sequence[int], part: str = DEFAULT_PART,
                 part_seed: int = DEFAULT_PART_SEED, cache: Path = DEFAULT_CACHE,
                 crops: Sequence[float] = DEFAULT_CROPS, width: int = 640, height: int = 480,
                 types: Any = None, progress: Callable[[Iterable], Iterable] | None = None
                 ) -> list[BenchScene]:
    """Generated bins with ``parts_counts`` copies each (cached), plus the crop scenes."""
    types = types or _message_types()
    scenes: list[BenchScene] = []
    counts = list(parts_counts)
    for n in (progress or (lambda it: it))(counts):
        path = synth_scene_path(cache, part, part_seed, n)
        if (width, height) != (640, 480):
            path = path.with_name(path.stem + f"_{width}x{height}.npz")

        def generate(n: int = n) -> dict:
            from fpcc_ros.training.synth import generate_scene  # training dependency (pybullet)
            return generate_scene(part, num_parts=n, seed=SYNTH_SEED + n, part_seed=part_seed,
                                  width=width, height=height)

        data = load_or_generate(path, generate)
        points, instance = data["points"], data["instance"]
        radius = float(np.asarray(data["part_radius"]).reshape(-1)[0])
        threshold = visible_threshold(points.shape[0] * points.shape[1])
        name = f"synth/{part}_p{part_seed}/n{n:02d}"
        scenes.append(BenchScene(name, "synth", camera_cloud(points, types), radius,
                                 instance.reshape(-1).astype(np.int64),
                                 num_parts=int(data["num_parts"]), min_visible=threshold,
                                 center_score=data["center_score"].reshape(-1)))
        if n == CROP_PARTS or (CROP_PARTS not in counts and n == counts[-1]):
            for fraction in crops:
                h, w = points.shape[:2]
                ch, cw = (max(1, round(s * math.sqrt(fraction))) for s in (h, w))
                top, left = (h - ch) // 2, (w - cw) // 2
                window = (slice(top, top + ch), slice(left, left + cw))
                # a crop keeps the sensor resolution: the full-frame visibility threshold applies
                scenes.append(BenchScene(f"{name}/crop{round(100 * fraction)}", "crop",
                                         camera_cloud(points[window], types), radius,
                                         instance[window].reshape(-1).astype(np.int64),
                                         num_parts=None, min_visible=threshold))
    return scenes


def demo_scenes(bag: Path = DEMO_BAG, cache: Path = DEFAULT_CACHE, ground_truth: bool = True,
                types: Any = None) -> list[BenchScene]:
    """The demo bag's frames; ground truth regenerated from its seeds when it matches."""
    types = types or _message_types()
    info_path = Path(bag).with_suffix(".json")
    info = json.loads(info_path.read_text()) if info_path.is_file() else {}
    radius = float(info.get("part_radius", 0.0)) or None
    msgs = _bag_clouds(Path(bag), types)
    gts: list[tuple[np.ndarray | None, str, int | None]] = [(None, "no ground truth", None)] * len(msgs)
    if ground_truth:
        gts = _demo_ground_truth(msgs, info, Path(cache))
    scenes = []
    for i, (msg, (gt, note, parts)) in enumerate(zip(msgs, gts)):
        h, w = int(msg.height), int(msg.width)
        scenes.append(BenchScene(f"demo/{i}", "demo", msg, radius or 0.05, gt, gt_note=note,
                                 num_parts=parts, min_visible=visible_threshold(h * w)))
    return scenes


def _bag_clouds(bag: Path, types: Any) -> list[Any]:
    from msg_tools.bag import pick_cloud_topic, read_messages
    from msg_tools.msg_types import ROSBAGS

    topic = pick_cloud_topic(bag, None)
    msgs = [msg for _, _, _, msg in read_messages(bag, [topic])]
    if types is ROSBAGS:
        return msgs
    from rclpy.serialization import deserialize_message  # the bytes a subscriber would get
    from sensor_msgs.msg import PointCloud2

    return [deserialize_message(bytes(ROSBAGS.typestore.serialize_cdr(m, "sensor_msgs/msg/PointCloud2")),
                                PointCloud2) for m in msgs]


# scripts/make_demo_bag.py draws each frame's number of parts from this range (its --parts)
DEMO_PARTS_RANGE = (22, 30)


def _demo_ground_truth(msgs: list[Any], info: dict, cache: Path
                       ) -> list[tuple[np.ndarray | None, str, int | None]]:
    """Ground truth of the demo frames, regenerated with scripts/make_demo_bag.py's seeds.

    Trusted only when the regenerated cloud is the bag's (same no-return pixels, points within
    the bag's 13-bit mantissa rounding); otherwise the frame has no ground truth and says why.
    """
    from msg_tools.point_cloud2 import read_xyz

    need = ("part", "part_seed", "seed")
    if not all(k in info for k in need):
        return [(None, f"bags/demo.json lacks {need}", None)] * len(msgs)
    rng = np.random.default_rng(int(info["seed"]))
    out = []
    for i, msg in enumerate(msgs):
        parts = int(rng.integers(*DEMO_PARTS_RANGE))
        path = Path(cache) / f"demo_{info['part']}_p{info['part_seed']}_n{parts}_s{info['seed'] + i}.npz"

        def generate(parts: int = parts, i: int = i) -> dict:
            from fpcc_ros.training.synth import generate_scene
            return generate_scene(info["part"], num_parts=parts, seed=int(info["seed"]) + i,
                                  part_seed=int(info["part_seed"]))

        try:
            data = load_or_generate(path, generate)
        except ImportError as exc:
            out.append((None, f"cannot regenerate ground truth ({exc})", None))
            continue
        bag_xyz = read_xyz(msg)
        gen_xyz = data["points"].reshape(-1, 3)
        same_holes = bag_xyz.shape == gen_xyz.shape and np.array_equal(
            np.isfinite(bag_xyz).all(1), np.isfinite(gen_xyz).all(1))
        ok = same_holes and np.nanmax(np.abs(bag_xyz - gen_xyz)) <= 1e-3
        out.append((data["instance"].reshape(-1).astype(np.int64), "", int(data["num_parts"]))
                   if ok else (None, "regenerated scene differs from the bag", None))
    return out


# ---------------------------------------------------------------------------------------------
# measurement
# ---------------------------------------------------------------------------------------------
@dataclass
class SceneRun:
    """Everything measured on one scene."""

    name: str
    kind: str
    points: int
    valid_points: int
    network_points: int
    gt_instances: int | None        # visible ground-truth instances
    num_parts: int | None
    predicted: int
    stages_ms: dict[str, list[float]]
    counts: InstanceCounts | None
    peak_rss_mb: float
    gt_note: str = ""
    full_res: dict[str, Any] | None = None
    inferred_points: int = 0        # points run through the network, halos included

    def stat(self, stage: str, q: float = 50.0) -> float:
        values = self.stages_ms.get(stage)
        return float(np.percentile(values, q)) if values else float("nan")

    def to_json(self) -> dict[str, Any]:
        return {
            "scene": self.name, "kind": self.kind, "points": self.points,
            "valid_points": self.valid_points, "network_points": self.network_points,
            "inferred_points": self.inferred_points,
            "gt_instances_visible": self.gt_instances, "num_parts": self.num_parts,
            "predicted_instances": self.predicted,
            "stages_ms": {s: {"median": self.stat(s), "p90": self.stat(s, 90.0), "runs": v}
                          for s, v in self.stages_ms.items()},
            "accuracy": (None if self.counts is None else
                         {**self.counts.summary(), "protocol": "visible"}),
            "ground_truth": self.gt_note or "yes",
            "peak_rss_mb": self.peak_rss_mb,
            "full_res": self.full_res,
        }


def reset_peak_rss() -> bool:
    """Reset this process's VmHWM (Linux >= 4.0), so the next reading is this scene's peak."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float:
    """VmHWM of this process in MB (the peak since the last reset), else ru_maxrss."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def scene_accuracy(scene: BenchScene, labels: np.ndarray) -> InstanceCounts | None:
    """Visible-protocol counts over the points with a measurement (as `fpcc eval` does)."""
    if scene.gt is None:
        return None
    from msg_tools.point_cloud2 import read_xyz

    finite = np.isfinite(read_xyz(scene.msg)).all(axis=1)
    return scene_counts(np.asarray(labels).reshape(-1)[finite], scene.gt[finite], "visible",
                        min_visible=scene.min_visible)


def visible_gt_instances(scene: BenchScene) -> int | None:
    if scene.gt is None:
        return None
    sizes = np.bincount(scene.gt)
    sizes[0] = 0
    return int((sizes >= scene.min_visible).sum())


def measure_scene(scene: BenchScene, pipeline: Any, runs: int, warmup: int = 1,
                  full_res_pipeline: Any = None) -> SceneRun:
    """``warmup`` untimed runs, then ``runs`` timed ones of the node's per-frame function."""
    from fpcc_ros.frame import process_cloud

    pipeline = _at_radius(pipeline, scene.part_radius)
    types = _message_types()
    reset_peak_rss()
    for _ in range(warmup):
        process_cloud(scene.msg, pipeline, types)
    stages: dict[str, list[float]] = {}
    out = None
    for _ in range(runs):
        out = process_cloud(scene.msg, pipeline, types)
        for stage, ms in out.timings_ms.items():
            stages.setdefault(stage, []).append(float(ms))
    assert out is not None
    result = out.result
    run = SceneRun(name=scene.name, kind=scene.kind, points=scene.num_points,
                   valid_points=result.num_valid, network_points=result.num_network_points,
                   gt_instances=visible_gt_instances(scene), num_parts=scene.num_parts,
                   predicted=result.num_instances, stages_ms=stages,
                   counts=scene_accuracy(scene, result.labels), peak_rss_mb=peak_rss_mb(),
                   gt_note=scene.gt_note,
                   inferred_points=int(getattr(result, "num_inferred_points", 0)))
    if full_res_pipeline is not None and scene.gt is not None:
        full = _at_radius(full_res_pipeline, scene.part_radius)
        t0 = time.perf_counter()
        full_out = process_cloud(scene.msg, full, types)
        counts = scene_accuracy(scene, full_out.result.labels)
        run.full_res = {"total_ms": (time.perf_counter() - t0) * 1e3,
                        "network_points": full_out.result.num_network_points,
                        "inferred_points": int(getattr(full_out.result, "num_inferred_points", 0)),
                        "predicted_instances": full_out.result.num_instances,
                        "accuracy": counts.summary() if counts is not None else None}
    return run


def _at_radius(pipeline: Any, radius: float) -> Any:
    """The pipeline at this scene's part radius (a shallow copy sharing the model)."""
    import copy

    if pipeline.config.part_radius == radius:
        return pipeline
    clone = copy.copy(pipeline)
    clone.config = pipeline.config.replace(part_radius=radius)
    return clone


# ---------------------------------------------------------------------------------------------
# NMS + clustering alone, at a size the goals name (100k points, 40 instances)
# ---------------------------------------------------------------------------------------------
# NMS settings of the NMS + clustering case, fixed so that its figure compares across models and
# calibrations: on the case's ground-truth center scores they give about one center per visible
# part (40 parts: 42 centers). The card's θ/γ suit its network's scores; at the shipped card's
# γ 1.0 the same case kept 19 centers for 40 parts, timing a different problem.
POSTPROCESS_SCORE_THRESHOLD = 0.5
POSTPROCESS_SCREENING_FACTOR = 0.7


def postprocess_case(scene: BenchScene, points: int = 100_000, seed: int = 0,
                     embedding_dim: int = 128) -> dict[str, np.ndarray | float]:
    """``points`` valid points of a labelled scene with the ground-truth center scores and
    embeddings a trained network would give: one direction per instance, 2 apart (beyond the
    loss's eps2 = 1), plus noise of norm ~0.25, so points of one instance lie within eps1 = 0.5
    of each other as the hinge asks (with noise of norm ~0.57 the calibrated feature gate of
    0.75 rejected nearly every point and the case scored P 0)."""
    from msg_tools.point_cloud2 import read_xyz

    assert scene.gt is not None and scene.center_score is not None
    xyz = read_xyz(scene.msg)
    finite = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(finite, size=min(points, len(finite)), replace=False))
    gt = scene.gt[pick]
    directions = rng.normal(size=(int(gt.max()) + 1, embedding_dim))
    directions *= 2.0 / np.linalg.norm(directions, axis=1, keepdims=True)
    noise = rng.normal(scale=0.25 / np.sqrt(embedding_dim), size=(len(pick), embedding_dim))
    embedding = directions[gt] + noise
    return {"xyz": xyz[pick].astype(np.float64), "score": scene.center_score[pick],
            "embedding": embedding.astype(np.float32), "gt": gt,
            "part_radius": scene.part_radius}


def measure_postprocess(case: dict, runs: int, score_threshold: float = 0.6,
                        screening_factor: float = 1.0, feature_gate: float = 1.0,
                        center_prototype: float = 0.0, center_merge: float = 0.0
                        ) -> dict[str, Any]:
    """Median/p90 of NMS and of the clustering step as the pipeline runs it (center prototypes
    and merging when the settings ask for them, nearest-center assignment) on one case, plus
    sanity counts."""
    from fpcc_ros.clustering import (assign_to_center_points, center_prototypes,
                                     close_center_pairs, merge_labels)
    from fpcc_ros.nms import nms_centers

    xyz, score, emb, radius = case["xyz"], case["score"], case["embedding"], case["part_radius"]
    nms_ms, assign_ms = [], []
    centers = labels = None
    for i in range(runs + 1):
        t0 = time.perf_counter()
        centers = nms_centers(xyz, score, score_threshold, screening_factor * radius)
        t1 = time.perf_counter()
        center_emb = center_prototypes(xyz, emb, centers, center_prototype * radius)
        labels = assign_to_center_points(xyz, emb, xyz[centers], center_emb, radius, feature_gate)
        if center_merge > 0 and len(centers) > 1:
            labels = merge_labels(labels, len(centers), close_center_pairs(
                xyz[centers], center_emb, radius, center_merge))
        t2 = time.perf_counter()
        if i:  # the first run warms caches
            nms_ms.append((t1 - t0) * 1e3)
            assign_ms.append((t2 - t1) * 1e3)
    total = np.add(nms_ms, assign_ms)
    counts = scene_counts(labels, case["gt"], "paper")
    return {"points": len(xyz), "candidates": int((score > score_threshold).sum()),
            "score_threshold": score_threshold, "screening_factor": screening_factor,
            "centers": len(centers), "gt_instances": int(len(np.unique(case["gt"][case["gt"] > 0]))),
            "center_prototype": center_prototype, "center_merge": center_merge,
            "nms_ms": _quantiles(nms_ms), "assign_ms": _quantiles(assign_ms),
            "total_ms": _quantiles(total), "accuracy": counts.summary()}


def _quantiles(values: Sequence[float]) -> dict[str, float]:
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)),
            "min": float(np.min(values))} if len(values) else {}


# ---------------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------------
@dataclass
class BenchReport:
    scenes: list[SceneRun]
    machine: dict[str, Any]
    model: dict[str, Any]
    config: dict[str, Any]
    runs: int
    postprocess: dict[str, Any] | None = None
    dds: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)
    variants: list[dict[str, Any]] = field(default_factory=list)  # see run_variants

    # -- derived figures ---------------------------------------------------------------------
    def synth(self) -> list[SceneRun]:
        return [s for s in self.scenes if s.kind == "synth"]

    def clutter(self) -> list[SceneRun]:
        lo, hi = CLUTTER_PARTS
        return [s for s in self.synth() if s.num_parts is not None and lo <= s.num_parts <= hi]

    def totals(self, scenes: Iterable[SceneRun]) -> InstanceCounts | None:
        counted = [s.counts for s in scenes if s.counts is not None]
        return sum(counted, InstanceCounts()) if counted else None

    def full_res_totals(self, scenes: Iterable[SceneRun]) -> InstanceCounts | None:
        done = [s.full_res["accuracy"] for s in scenes if s.full_res and s.full_res["accuracy"]]
        if not done:
            return None
        return InstanceCounts(true_positives=sum(a["true_positives"] for a in done),
                              predictions=sum(a["predictions"] for a in done),
                              ground_truths=sum(a["ground_truths"] for a in done))

    def growth(self) -> dict[str, Any] | None:
        """End-to-end latency growth from the fewest to the most parts (synth scenes)."""
        synth = sorted((s for s in self.synth() if s.num_parts is not None), key=lambda s: s.num_parts)
        if len(synth) < 2:
            return None
        lo, hi = synth[0], synth[-1]
        return {"from_parts": lo.num_parts, "to_parts": hi.num_parts,
                "from_ms": lo.stat("total"), "to_ms": hi.stat("total"),
                "growth": hi.stat("total") / lo.stat("total") - 1.0,
                # why it grows: points through the network (halos included) vs the O(nm) part
                "inferred_points_growth": hi.inferred_points / max(lo.inferred_points, 1) - 1.0,
                "ms_per_1k_inferred_points": [lo.stat("total") / max(lo.inferred_points, 1) * 1e3,
                                              hi.stat("total") / max(hi.inferred_points, 1) * 1e3],
                "nms_cluster_ms": [lo.stat("nms") + lo.stat("cluster"),
                                   hi.stat("nms") + hi.stat("cluster")]}

    def linearity(self) -> dict[str, Any] | None:
        """Least-squares line of end-to-end latency on valid points over every scene."""
        pts = np.array([s.valid_points for s in self.scenes], float)
        ms = np.array([s.stat("total") for s in self.scenes], float)
        if len(pts) < 3 or np.ptp(pts) == 0:
            return None
        slope, intercept = np.polyfit(pts, ms, 1)
        fit = slope * pts + intercept
        r2 = 1.0 - float(((ms - fit) ** 2).sum()) / max(float(((ms - ms.mean()) ** 2).sum()), 1e-12)
        return {"ms_per_100k_valid_points": float(slope * 1e5), "intercept_ms": float(intercept),
                "r2": r2}

    def goals(self) -> list[dict[str, Any]]:
        """The issue's goals with the measured figure and a verdict (None = not measured)."""
        goals: list[dict[str, Any]] = []
        clutter = self.clutter()
        e2e = float(np.median([s.stat("total") for s in clutter])) if clutter else float("nan")
        goals.append(_goal("end to end, cluttered bin (20-30 parts), median", e2e, "ms", 200.0))
        goals.append(_goal("stretch: end to end, cluttered bin", e2e, "ms", 120.0))
        piles = [s for s in self.scenes if s.stages_ms.get("fragments")]
        if piles:   # the connected clustering's geometry, on the organized 640x480 camera piles
            goals.append(_goal("connected clustering's fragment step, median over the piles",
                               float(np.median([s.stat("fragments") for s in piles])), "ms",
                               10.0))
        fast, full = self.totals(clutter), self.full_res_totals(clutter)
        if fast is not None and full is not None:
            worst = max(abs(fast.precision - full.precision), abs(fast.recall - full.recall))
            goals.append(_goal("precision/recall vs full resolution, cluttered bins (points)",
                               100 * worst, "pt", 2.0))
            # what the goal guards against is a speed-up that costs accuracy: the loss alone
            loss = max(full.precision - fast.precision, full.recall - fast.recall, 0.0)
            goals.append(_goal("  the same, loss only (fast path below full resolution)",
                               100 * loss, "pt", 2.0))
        else:
            goals.append({"goal": "precision/recall vs full resolution (run with --full-res)",
                          "value": None, "unit": "pt", "limit": 2.0, "ok": None})
        if self.postprocess:
            goals.append(_goal(f"NMS + clustering, {self.postprocess['points'] // 1000}k points, "
                               f"{self.postprocess['gt_instances']} instances, median",
                               self.postprocess["total_ms"]["median"], "ms", 10.0))
            plain = self.postprocess.get("paper_rule")
            if plain:
                goals.append(_goal("  the same with the paper's clustering (each center's own "
                                   "embedding, no merging)", plain["total_ms"]["median"], "ms",
                                   10.0))
        growth = self.growth()
        if growth:
            goals.append(_goal(f"latency growth {growth['from_parts']} -> {growth['to_parts']} "
                               "parts", 100 * growth["growth"], "%", 15.0))
            per_point = growth["ms_per_1k_inferred_points"]
            if per_point[0] > 0:
                goals.append(_goal(f"  the same per point through the network (the O(nm) claim; "
                                   f"network points {100 * growth['inferred_points_growth']:+.0f}%)",
                                   100 * (per_point[1] / per_point[0] - 1.0), "%", 15.0))
        peak = max((s.peak_rss_mb for s in self.scenes), default=float("nan"))
        goals.append(_goal("peak RSS of the benchmark process (node: see --dds)", peak, "MB", 600.0))
        if self.dds:
            for rate in self.dds.get("rates", []):
                goals.append(_goal(f"DDS {rate['rate_hz']:g} Hz: node peak RSS",
                                   rate["node_rss_peak_mb"], "MB", 600.0))
                goals.append({"goal": f"DDS {rate['rate_hz']:g} Hz: keeps up or drops stale "
                                      "frames, no queue", "value": rate["verdict"], "unit": "",
                              "limit": None, "ok": rate["no_queue"]})
        return goals

    # -- output --------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        clutter = self.clutter()
        fast, full = self.totals(clutter), self.full_res_totals(clutter)
        return {
            "format": REPORT_FORMAT, "machine": self.machine, "model": self.model,
            "pipeline": self.config, "runs_per_scene": self.runs,
            "scenes": [s.to_json() for s in self.scenes],
            "summary": {
                "clutter_end_to_end_ms": {
                    "median": float(np.median([s.stat("total") for s in clutter])) if clutter else None,
                    "p90": float(np.median([s.stat("total", 90) for s in clutter])) if clutter else None},
                "clutter_accuracy": fast.summary() if fast else None,
                "clutter_accuracy_full_res": full.summary() if full else None,
                "all_accuracy": (t.summary() if (t := self.totals(self.scenes)) else None),
                "growth": self.growth(), "linearity": self.linearity(),
                "peak_rss_mb": max((s.peak_rss_mb for s in self.scenes), default=None),
            },
            "postprocess": self.postprocess, "dds": self.dds, "goals": self.goals(),
            "variants": [{**v, "scenes": [r.to_json() for r in v["scenes"]]} for v in self.variants],
            "notes": self.notes,
        }

    def table(self) -> str:
        stages = [s for s in STAGES if any(s in r.stages_ms for r in self.scenes)]
        name_w = max([len(s.name) for s in self.scenes] + [5])
        head = (f"{'scene':<{name_w}} {'valid':>7} {'net':>6} {'inf':>6} {'GT':>3} {'pred':>4} "
                + " ".join(f"{_short(s):>9}" for s in stages) + f" {'RSS MB':>7} {'P':>6} {'R':>6}")
        lines = [f"median / p90 ms over {self.runs} warm runs per scene (net = points after "
                 f"voxel downsampling, inf = points run through the network, halos included; "
                 f"GT = visible ground-truth instances)",
                 head, "-" * len(head)]
        for r in self.scenes:
            cells = " ".join(f"{_pair(r.stat(s), r.stat(s, 90)):>9}" for s in stages)
            p = f"{r.counts.precision:>6.3f} {r.counts.recall:>6.3f}" if r.counts else f"{'n/a':>6} {'n/a':>6}"
            gt = "-" if r.gt_instances is None else str(r.gt_instances)
            lines.append(f"{r.name:<{name_w}} {r.valid_points:>7} {r.network_points:>6} "
                         f"{r.inferred_points:>6} {gt:>3} "
                         f"{r.predicted:>4} {cells} {r.peak_rss_mb:>7.0f} {p}")
        full_rows = [r for r in self.scenes if r.full_res]
        if full_rows:
            lines += ["", "full resolution (voxel_size 0, every valid point through the network), one run:"]
            for r in full_rows:
                a = r.full_res["accuracy"] or {}
                lines.append(f"  {r.name:<{name_w}} {r.full_res['total_ms']:>8.0f} ms, "
                             f"{r.full_res['network_points']} network points, P "
                             f"{a.get('precision', float('nan')):.3f} R {a.get('recall', float('nan')):.3f}"
                             + (f"  (fast path P {r.counts.precision:.3f} R {r.counts.recall:.3f})"
                                if r.counts else ""))
        return "\n".join(lines)

    def markdown(self) -> str:
        """The per-scene table and the goals as Markdown (README / docs)."""
        stages = [s for s in ("decode", "valid", "downsample", "floor", "features", "inference",
                              "nms", "cluster", "fragments", "labels", "encode", "total")
                  if any(s in r.stages_ms for r in self.scenes)]
        m = self.machine
        out = [f"Machine: {_cpu_label(m)}, {m.get('cpus')} CPUs; onnxruntime {m.get('onnxruntime')} "
               f"{', '.join(m.get('providers') or [])}; model `{self.model.get('name')}`"
               + (" (untrained)" if self.model.get("untrained") else "")
               + (f", graph: {self.model['graph']}" if self.model.get("graph") else "")
               + _stride_label(self.config) + f"; median / p90 of {self.runs} warm runs, ms.", "",
               "| scene | valid pts | pts through net | GT | pred | " + " | ".join(_short(s) for s in stages)
               + " | peak RSS MB | P | R |",
               "|" + "---|" * (len(stages) + 8)]
        for r in self.scenes:
            cells = " | ".join(_pair(r.stat(s), r.stat(s, 90)) for s in stages)
            pr = (f"{r.counts.precision:.3f} | {r.counts.recall:.3f}" if r.counts else "n/a | n/a")
            gt = "-" if r.gt_instances is None else str(r.gt_instances)
            out.append(f"| {r.name} | {r.valid_points} | {r.inferred_points} | {gt} | {r.predicted} | "
                       f"{cells} | {r.peak_rss_mb:.0f} | {pr} |")
        out += ["", "| goal | measured | limit | verdict |", "|---|---|---|---|"]
        for g in self.goals():
            value = g["value"]
            shown = (f"{value:.1f} {g['unit']}" if isinstance(value, (int, float)) and value == value
                     else str(value))
            limit = f"<= {g['limit']:g} {g['unit']}" if g["limit"] is not None else ""
            out.append(f"| {g['goal']} | {shown} | {limit} | "
                       f"{ {True: 'pass', False: 'FAIL', None: '-'}[g['ok']]} |")
        if self.variants or any(r.full_res for r in self.scenes):
            out += ["", "```", self.variants_table(), "```"]
        if self.dds:
            out += ["", f"Live node over DDS ({self.dds['clouds']}; {self.dds['transport']}); "
                    "latency = publish -> last output received, ms.", "",
                    "| camera rate | sent | outputs | output rate | dropped | latency median / p90 / max "
                    "| node receive-to-publish median | frame age trend | node RSS median / peak MB | verdict |",
                    "|---|---|---|---|---|---|---|---|---|---|"]
            for r in self.dds["rates"]:
                lat = r["latency_ms"]
                node = r["node"].get("node_latency_median_ms")
                out.append(f"| {r['rate_hz']:g} Hz | {r['frames_sent']} | {r['outputs']} | "
                           f"{r['output_rate_hz']:.2f} Hz | {r['dropped']} | "
                           f"{lat.get('median', float('nan')):.0f} / {lat.get('p90', float('nan')):.0f} / "
                           f"{lat.get('max', float('nan')):.0f} | "
                           f"{'-' if node is None else f'{node:.0f}'} | "
                           f"{r['age_trend_ms_per_s']:+.1f} ms/s | "
                           f"{r['node_rss_mb'].get('median', float('nan')):.0f} / "
                           f"{r['node_rss_peak_mb']:.0f} | {r['verdict']} |")
        out += [""] + [f"Note: {n}" for n in self.notes]
        return "\n".join(out) + "\n"

    def variants_table(self) -> str:
        """The default settings and each variant side by side: latency, network work, accuracy
        (counts summed over the scenes with ground truth) and the change against full resolution."""
        rows = [{"name": "default", "scenes": self.scenes}] + self.variants
        full = self.full_res_totals(self.scenes)
        w = max([len(row["name"]) for row in rows] + [25])
        head = (f"{'settings':<{w}} {'clutter ms':>10} {'inferred':>9} {'P':>6} {'R':>6} "
                f"{'clutter P':>9} {'clutter R':>9}" + (f" {'dP full':>8} {'dR full':>8}" if full else ""))
        lines = ["settings compared on the same scenes (inferred = mean points through the "
                 "network per scene; P/R visible protocol, counts summed)", head, "-" * len(head)]
        lo, hi = CLUTTER_PARTS
        for row in rows:
            scenes = row["scenes"]
            clutter = [r for r in scenes if r.kind == "synth" and r.num_parts is not None
                       and lo <= r.num_parts <= hi]
            ms = float(np.median([r.stat("total") for r in clutter])) if clutter else float("nan")
            inferred = float(np.mean([r.inferred_points for r in scenes])) if scenes else float("nan")
            every, dense = self.totals(scenes), self.totals(clutter)
            cells = (f"{every.precision:>6.3f} {every.recall:>6.3f}" if every else f"{'n/a':>6} {'n/a':>6}")
            cells += (f" {dense.precision:>9.3f} {dense.recall:>9.3f}" if dense else f" {'n/a':>9} {'n/a':>9}")
            if full:
                cells += (f" {100 * (every.precision - full.precision):>+8.1f} "
                          f"{100 * (every.recall - full.recall):>+8.1f}" if every else "")
            lines.append(f"{row['name']:<{w}} {ms:>10.0f} {inferred:>9.0f} {cells}")
        if full:
            lines.append(f"{'full resolution (one run)':<{w}} {'':>10} "
                         f"{np.mean([r.full_res['inferred_points'] for r in self.scenes if r.full_res]):>9.0f} "
                         f"{full.precision:>6.3f} {full.recall:>6.3f}   (dP/dR in points)")
        return "\n".join(lines)

    def summary(self) -> str:
        lines = []
        m = self.machine
        reference, host = probe_reference(m)
        lines.append(f"machine: {_cpu_label(m)}, {m.get('cpus')} CPUs visible, onnxruntime "
                     f"{m.get('onnxruntime')} {m.get('providers')}, threads {m.get('threads')}"
                     + (f", speed probe {m['speed_probe_ms']:.1f} ms ({host}: ~{reference:g})"
                        if m.get("speed_probe_ms") else "")
                     + (f", malloc {m['heap']}" if m.get("heap") else ""))
        lines.append(f"model: {self.model.get('path')} ({self.model.get('name')})"
                     + _stride_label(self.config)
                     + ("  UNTRAINED: accuracy meaningless" if self.model.get("untrained") else ""))
        if self.model.get("health"):
            lines.append(f"model health: {self.model['health']}")
        if self.postprocess:
            p = self.postprocess
            lines.append(f"NMS + clustering alone: {p['points']} points, {p['gt_instances']} GT "
                         f"instances, {p['candidates']} candidates -> {p['centers']} centers "
                         f"(θ {p.get('score_threshold', '?')}, γ {p.get('screening_factor', '?')}, "
                         f"fixed; gate and clustering steps from the card): NMS "
                         f"{_stat(p['nms_ms'])} ms, clustering (prototypes "
                         f"{p.get('center_prototype', 0)}, merge {p.get('center_merge', 0)}) "
                         f"{_stat(p['assign_ms'])} ms, total {_stat(p['total_ms'])} ms "
                         f"(median/p90); {_accuracy(p)}")
            if p.get("one_thread"):
                q = p["one_thread"]
                lines.append(f"  the same with the chunk loops on one thread: clustering "
                             f"{_stat(q['assign_ms'])} ms, total {_stat(q['total_ms'])} ms")
            if p.get("paper_rule"):
                q = p["paper_rule"]
                lines.append(f"  with the paper's clustering (own center embeddings, no merging):"
                             f" NMS {_stat(q['nms_ms'])} ms, assignment {_stat(q['assign_ms'])}"
                             f" ms, total {_stat(q['total_ms'])} ms; {_accuracy(q)}")
        growth = self.growth()
        if growth:
            lines.append(f"{growth['from_parts']} -> {growth['to_parts']} parts: end to end "
                         f"{growth['from_ms']:.0f} -> {growth['to_ms']:.0f} ms; points through the "
                         f"network {100 * growth['inferred_points_growth']:+.0f}%; per 1k such points "
                         f"{growth['ms_per_1k_inferred_points'][0]:.1f} -> "
                         f"{growth['ms_per_1k_inferred_points'][1]:.1f} ms; NMS + clustering "
                         f"{growth['nms_cluster_ms'][0]:.1f} -> {growth['nms_cluster_ms'][1]:.1f} ms")
        lin = self.linearity()
        if lin:
            lines.append(f"latency vs valid points: {lin['ms_per_100k_valid_points']:.1f} ms per "
                         f"100k points + {lin['intercept_ms']:.0f} ms (R^2 {lin['r2']:.2f})")
        totals = self.totals(self.scenes)
        if totals:
            lines.append(f"accuracy over scenes with ground truth (visible protocol): P "
                         f"{totals.precision:.3f} R {totals.recall:.3f} "
                         f"({totals.true_positives}/{totals.predictions}/{totals.ground_truths} TP/pred/GT)")
        lines.append("goals:")
        for g in self.goals():
            verdict = {True: "PASS", False: "FAIL", None: "  - "}[g["ok"]]
            value = g["value"]
            shown = (f"{value:.1f} {g['unit']}" if isinstance(value, (int, float)) and
                     not (isinstance(value, float) and math.isnan(value)) else str(value))
            limit = f" (<= {g['limit']:g} {g['unit']})" if g["limit"] is not None else ""
            lines.append(f"  [{verdict}] {g['goal']}: {shown}{limit}")
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


def _run_from_json(s: dict[str, Any]) -> SceneRun:
    acc = s.get("accuracy")
    counts = None if not acc else InstanceCounts(
        true_positives=acc["true_positives"], predictions=acc["predictions"],
        ground_truths=acc["ground_truths"])
    return SceneRun(name=s["scene"], kind=s["kind"], points=s["points"],
                    valid_points=s["valid_points"], network_points=s["network_points"],
                    gt_instances=s["gt_instances_visible"], num_parts=s["num_parts"],
                    predicted=s["predicted_instances"],
                    stages_ms={k: v["runs"] for k, v in s["stages_ms"].items()}, counts=counts,
                    peak_rss_mb=s["peak_rss_mb"],
                    gt_note="" if s.get("ground_truth") == "yes" else s.get("ground_truth", ""),
                    full_res=s.get("full_res"), inferred_points=s.get("inferred_points", 0))


def report_from_json(data: dict[str, Any]) -> BenchReport:
    """A report written by :func:`write_json`, to print, plot or tabulate again without rerunning
    (precision/recall come back from the counts; MUCov/MWCov sums are not kept)."""
    if data.get("format") != REPORT_FORMAT:
        raise ValueError(f"not a {REPORT_FORMAT} report (format {data.get('format')!r})")
    return BenchReport(
        scenes=[_run_from_json(s) for s in data["scenes"]], machine=data["machine"],
        model=data["model"], config=data["pipeline"], runs=data["runs_per_scene"],
        postprocess=data.get("postprocess"), dds=data.get("dds"), notes=data.get("notes", []),
        variants=[{**v, "scenes": [_run_from_json(s) for s in v["scenes"]]}
                  for v in data.get("variants", [])])


def _goal(name: str, value: float, unit: str, limit: float) -> dict[str, Any]:
    ok = None if value is None or (isinstance(value, float) and math.isnan(value)) else value <= limit
    return {"goal": name, "value": value, "unit": unit, "limit": limit, "ok": ok}


def _short(stage: str) -> str:
    return {"downsample": "voxel", "inference": "onnx", "features": "feat+knn"}.get(stage, stage)


def _pair(median: float, p90: float) -> str:
    return f"{median:.0f}/{p90:.0f}" if median >= 10 else f"{median:.1f}/{p90:.1f}"


def _stride_label(config: dict[str, Any]) -> str:
    """The global feature's stride when it is not every point (an approximation: README)."""
    stride = config.get("global_stride", 1)
    return f", global feature over 1 in {stride} points" if stride != 1 else ""


def _stat(quantiles: dict[str, float]) -> str:
    """A ``_quantiles`` dict as median/p90."""
    return _pair(quantiles["median"], quantiles["p90"])


def _accuracy(case: dict[str, Any]) -> str:
    return f"P {case['accuracy']['precision']:.3f} R {case['accuracy']['recall']:.3f}"


# A numpy pass over 100k x 128 float32 (one dot product per row) on an idle machine, per host
# kind of this 2-core VM: 2.3-2.8 ms on the AVX-512 host of the README's table, 3.4-5.2 ms on
# the AVX2-only host (2026-12-02: 4.4-5.2 in 12 probes at 21:28, 3.4 in the bench at 22:55).
# Figures measured while it reads well above its host's reference are inflated by load
# (compare ratios within one run). The AVX2 host needs its own reference: against the table's
# it read as "1.9x inflated" when idle.
REFERENCE_PROBE_MS = 2.6
REFERENCE_PROBE_MS_AVX2 = 4.0
SLOW_PROBE_FACTOR = 1.3


def probe_reference(machine: dict[str, Any]) -> tuple[float, str]:
    """The idle speed probe of this machine's host kind (ms) and the kind's name: AVX2-only
    hosts have their own; AVX-512 hosts, and machines whose vector extensions are unknown, are
    compared with the README table's."""
    vector = machine.get("cpu_vector")
    if vector is not None and "avx512f" not in vector:
        return REFERENCE_PROBE_MS_AVX2, "an idle AVX2 host"
    return REFERENCE_PROBE_MS, "the README table's days"


def speed_probe(repeats: int = 15) -> float:
    """Median ms of one numpy pass over a 100k x 128 float32 array: memory speed, which NMS,
    clustering and most stages around the network are bound by. Recorded with every report so
    that figures from a slow day (a shared VM's neighbours, no AVX-512) can be told apart."""
    rng = np.random.default_rng(0)
    rows = rng.random((100_000, 128), dtype=np.float32)
    weights = rng.random(128, dtype=np.float32)
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        np.einsum("ij,j->i", rows, weights)
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times[1:]))  # the first pass warms caches


# The vector extensions that decide the network's speed on a CPU. The README table's host had
# AVX-512 with BF16 (the shipped model trained in bf16 on it); on a host of this VM without
# AVX-512 (AVX2 only) the whole path runs about 2x slower (2026-12-02, `fpcc bench --runs 3`:
# cluttered bin 301 ms against the table's 179 with older code, which the exact changes since
# took about 0.8x off): another machine, not a busy one.
VECTOR_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_int8")


def cpu_description(cpuinfo: str) -> tuple[str, list[str]]:
    """The first CPU's model name and which of :data:`VECTOR_FLAGS` it has, from the text of
    /proc/cpuinfo."""
    model, flags = "", set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and not model:
            model = value.strip()
        elif key.strip() == "flags" and not flags:
            flags = set(value.split())
    return model, [f for f in VECTOR_FLAGS if f in flags]


def cpu_vendor(cpuinfo: str) -> str:
    """``GenuineIntel``, ``AuthenticAMD``, ... from /proc/cpuinfo's ``vendor_id`` ('' if none).
    Named beside every timing: Intel cores pay ~30x per denormal product, AMD cores little, so
    one model can be 7x slower on one vendor than on the other (issue 25)."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "vendor_id":
            return value.strip()
    return ""


def _cpu_label(machine: dict[str, Any]) -> str:
    """The CPU's vendor, name and vector extensions, e.g. "AuthenticAMD AMD EPYC (avx2 fma)"."""
    vector = machine.get("cpu_vector")
    vendor = machine.get("cpu_vendor")
    return (f"{vendor} " if vendor else "") + f"{machine.get('cpu')}" + (
        f" ({' '.join(vector) or 'no AVX2'})" if vector is not None else "")


def machine_info(pipeline: Any) -> dict[str, Any]:
    import onnxruntime as ort

    cpu, vector, vendor = platform.processor() or "", None, ""
    try:
        cpuinfo = Path("/proc/cpuinfo").read_text()
        model, vector = cpu_description(cpuinfo)
        cpu, vendor = model or cpu, cpu_vendor(cpuinfo)
    except OSError:
        pass
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:
        cpus = os.cpu_count()
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return {"cpu": cpu, "cpu_vendor": vendor, "cpu_vector": vector, "cpus": cpus,
            "load_avg_1m_at_start": load[0] if load else None,
            "python": platform.python_version(), "numpy": np.__version__,
            "onnxruntime": ort.__version__, "providers": pipeline.model.active_providers,
            "threads": getattr(pipeline.model, "threads", None), "platform": platform.platform(),
            "speed_probe_ms": speed_probe(), "heap": heap_setting()}


def heap_setting() -> str:
    """How this process's malloc treats freed frame memory (fpcc_ros.heap): `fpcc` and the node
    keep it; another process embedding the pipeline pays page faults on every frame."""
    from fpcc_ros import heap

    return ("retains freed memory (fpcc_ros.heap)" if heap.retained
            else "returns freed memory to the kernel (C library defaults)")


def model_info(pipeline: Any) -> dict[str, Any]:
    card = pipeline.model.card
    return {"path": str(pipeline.model.path), "name": card.name, "k": card.k,
            "untrained": bool((card.training or {}).get("untrained", False)),
            "graph": getattr(pipeline.model, "graph_notes", None),
            "health": pipeline.model.health_line() if hasattr(pipeline.model, "health_line") else None,
            "collapsed": bool(getattr(pipeline.model, "collapsed", False))}


def config_info(config: Any) -> dict[str, Any]:
    from dataclasses import asdict

    info = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()}
    info["effective_voxel_size"] = config.effective_voxel_size
    info["part_radius"] = "per scene"
    return info


# ---------------------------------------------------------------------------------------------
# plot
# ---------------------------------------------------------------------------------------------
def _style_axis(ax: Any, xlabel: str, ylabel: str, title: str, from_zero_x: bool = True) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if from_zero_x:
        ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def plot(report: BenchReport, path: Path) -> Path:
    """Latency vs number of instances (synth bins) and vs number of valid points (all scenes)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(17, 4.6))
    synth = sorted((s for s in report.synth() if s.num_parts is not None), key=lambda s: s.num_parts)
    if synth:
        x = [s.num_parts for s in synth]
        for stage, style in (("total", "o-"), ("inference", "s--"), ("features", "^--"),
                             ("nms", "v:"), ("cluster", "d:")):
            if all(stage in s.stages_ms for s in synth):
                med = np.array([s.stat(stage) for s in synth])
                p90 = np.array([s.stat(stage, 90) for s in synth])
                ax1.errorbar(x, med, yerr=np.vstack([np.zeros_like(med), p90 - med]), fmt=style,
                             capsize=3,
                             label=("end to end" if stage == "total" else stage))
        _style_axis(ax1, "parts in the bin (synthetic 640x480 scenes)",
                    "latency, ms (median, bar to p90)", "latency vs number of instances",
                    from_zero_x=False)
    markers = {"demo": ("D", "demo bag"), "synth": ("o", "synthetic bins"), "crop": ("s", "crops")}
    for kind, (marker, label) in markers.items():
        rows = [s for s in report.scenes if s.kind == kind]
        if rows:
            ax2.scatter([s.valid_points / 1e3 for s in rows], [s.stat("total") for s in rows],
                        marker=marker, label=label)
    lin = report.linearity()
    if lin:
        xs = np.linspace(0, max(s.valid_points for s in report.scenes), 50)
        ax2.plot(xs / 1e3, lin["intercept_ms"] + lin["ms_per_100k_valid_points"] * xs / 1e5, "k:",
                 label=f"fit: {lin['ms_per_100k_valid_points']:.0f} ms/100k pts + "
                       f"{lin['intercept_ms']:.0f} ms")
    for kind, (marker, label) in markers.items():
        rows = [s for s in report.scenes if s.kind == kind and s.inferred_points]
        if rows:
            ax3.scatter([s.inferred_points / 1e3 for s in rows], [s.stat("total") for s in rows],
                        marker=marker, label=label)
    _style_axis(ax3, "points through the network, halos included (thousands)",
                "end-to-end latency, ms (median)", "latency vs network work")
    _style_axis(ax2, "valid points (thousands)", "end-to-end latency, ms (median)",
                "latency vs number of valid points")
    m = report.machine
    fig.suptitle(f"fpcc bench: {m.get('cpus')} CPUs, onnxruntime {m.get('onnxruntime')}, "
                 f"{report.model.get('name')}" + (" (untrained)" if report.model.get("untrained") else ""),
                 fontsize=10)
    from fpcc_ros.render import save_figure
    return save_figure(fig, path)


# ---------------------------------------------------------------------------------------------
# the whole benchmark
# ---------------------------------------------------------------------------------------------
def run_bench(pipeline: Any, scenes: Sequence[BenchScene], runs: int = 5,
              full_res: bool = False, postprocess_scene: BenchScene | None = None,
              progress: Callable[[Iterable], Iterable] | None = None) -> BenchReport:
    """Measure every scene; optionally the full-resolution path and NMS + clustering alone."""
    full_pipeline = None
    if full_res:
        import copy
        full_pipeline = copy.copy(pipeline)
        full_pipeline.config = pipeline.config.replace(voxel_size=0.0)
    report = BenchReport(scenes=[], machine=machine_info(pipeline), model=model_info(pipeline),
                         config=config_info(pipeline.config), runs=runs)
    for scene in (progress or (lambda it: it))(list(scenes)):
        report.scenes.append(measure_scene(scene, pipeline, runs, full_res_pipeline=full_pipeline))
    if postprocess_scene is not None:
        case = postprocess_case(postprocess_scene)
        cfg = pipeline.config
        nms_settings = (POSTPROCESS_SCORE_THRESHOLD, POSTPROCESS_SCREENING_FACTOR)
        card_clustering = (cfg.feature_gate, cfg.center_prototype, cfg.center_merge)
        report.postprocess = {"scene": postprocess_scene.name,
                              **measure_postprocess(case, max(runs, 5), *nms_settings,
                                                    *card_clustering)}
        from fpcc_ros.clustering import chunk_threads
        with chunk_threads(1):   # what splitting the chunk loops across cores gains
            report.postprocess["one_thread"] = measure_postprocess(
                case, max(runs, 5), *nms_settings, *card_clustering)
        if cfg.center_prototype > 0 or cfg.center_merge > 0:
            # the extra clustering steps have a price: show the paper's rule beside them
            report.postprocess["paper_rule"] = measure_postprocess(
                case, max(runs, 5), *nms_settings, cfg.feature_gate)
    if report.machine.get("load_avg_1m_at_start") and report.machine["cpus"] and \
            report.machine["load_avg_1m_at_start"] > 0.5 * report.machine["cpus"]:
        report.notes.append(f"the machine was busy at the start (1-minute load "
                            f"{report.machine['load_avg_1m_at_start']:.1f} on "
                            f"{report.machine['cpus']} CPUs): timings are inflated")
    vector = report.machine.get("cpu_vector")
    if vector is not None and "avx512f" not in vector:
        report.notes.append("this CPU has no AVX-512 (the README table's host had AVX-512 with "
                            "BF16): on such a host the code runs about 2x slower end to end, "
                            "whatever the load; compare ratios within one run, not with the "
                            "table")
    probe = report.machine.get("speed_probe_ms")
    reference, host = probe_reference(report.machine)
    if probe and probe > SLOW_PROBE_FACTOR * reference:
        report.notes.append(f"this machine ran the speed probe in {probe:.1f} ms against "
                            f"~{reference:g} ms on {host}: timings are about "
                            f"{probe / reference:.1f}x inflated by load; compare ratios within "
                            "one run")
    graph = report.model.get("graph") or ""
    if not graph:
        report.notes.append("the model's graph is not rewritten for onnxruntime's CPU kernels: "
                            "scripts/optimize_onnx.py MODEL (exact) cuts its inference time by "
                            "about a third")
    elif "max-first" not in graph:
        report.notes.append("the model's graph predates the max-first rewrite: "
                            "scripts/optimize_onnx.py MODEL (bit-identical outputs) takes another "
                            "12-17% off its inference time")
    elif "global-stride" not in graph:
        report.notes.append("the model's graph takes no global_stride: scripts/optimize_onnx.py "
                            "MODEL adds it (exact at 1); at global_stride 4 the network takes "
                            "0.80-0.87x the time, an approximation (README, Parameters)")
    if report.model.get("collapsed"):
        report.notes.append("the model's network has collapsed (a layer more than 10% dead: "
                            "see 'model health'): its dead channels cost time for nothing and "
                            "its accuracy is not what a healthy network of this size gives")
    if report.model.get("untrained"):
        report.notes.append("the model is untrained: its timings are representative, its "
                            "precision/recall are not")
    return report


def parse_variant(text: str) -> dict[str, Any]:
    """``"block_halo=0.5,block_size=4096"`` -> pipeline config overrides (numbers parsed)."""
    overrides: dict[str, Any] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"variant {text!r}: {item!r} is not KEY=VALUE (e.g. block_halo=0.5)")
        try:
            number = float(value)
        except ValueError:
            overrides[key.strip()] = value.strip()   # a word, e.g. block_split=balanced
            continue
        overrides[key.strip()] = int(number) if number.is_integer() and "." not in value else number
    return overrides


def run_variants(report: BenchReport, pipeline: Any, scenes: Sequence[BenchScene],
                 variants: Sequence[str], runs: int,
                 progress: Callable[[Iterable], Iterable] | None = None) -> None:
    """Each variant's settings on the same scenes, appended to ``report.variants``."""
    for text in variants:
        import copy
        variant = copy.copy(pipeline)
        variant.config = pipeline.config.replace(**parse_variant(text))
        rows = [measure_scene(scene, variant, runs)
                for scene in (progress or (lambda it: it))(list(scenes))]
        report.variants.append({"name": text, "overrides": parse_variant(text),
                                "config": config_info(variant.config), "scenes": rows})


def write_json(report: BenchReport, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report.to_json(), indent=2, default=_json_default) + "\n")
    return path


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


if __name__ == "__main__":  # pragma: no cover - use `fpcc bench`
    sys.exit("use `fpcc bench`")
