"""The model card: the JSON beside every ONNX file that says how to feed it and what it is.

The runtime trusts the card for everything the ONNX graph cannot say (feature normalisation,
block size, voxel factor, default part radius and NMS settings), so it is validated strictly:
a card that disagrees with its model is a start-up error, never a silent mis-segmentation.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from fpcc_ros.features import FEATURE_NAMES, FEATURE_NAMES_WITH_NORMALS

CARD_FORMAT = "fpcc_ros/model-card/1"
EMBEDDING_DIM = 128
CLUSTERINGS = ("paper", "connected")   # the pipeline's clustering modes
MAX_GLOBAL_STRIDE = 16   # beyond 8 the shipped net already lost 2.6 F1 points (README)
MAX_FRAGMENT_CREASE = 1000.0   # 1/m: a 1 mm radius; sharper than any fold a depth camera resolves


class ModelCardError(ValueError):
    """A model card that is missing, unreadable or inconsistent."""


@dataclass(frozen=True)
class ModelCard:
    name: str
    k: int
    part_radius: float
    block_size: int = 4096
    voxel_factor: float = 0.08
    screening_factor: float = 1.0
    score_threshold: float = 0.6
    feature_gate: float = 1.0
    center_merge: float = 0.0   # merge centers within d_max closer than this in embedding space
    center_prototype: float = 0.0  # part radii around a center whose like points' mean embedding
    #   stands for it (clustering.center_prototypes); 0 = the center point's own
    embedding_dim: int = EMBEDDING_DIM
    knn_near: int = 0    # 0 = plain kNN; else the dilated neighbourhood of features.neighbour_columns
    knn_reach: int = 0
    global_stride: int = 1   # the global feature's max over every s-th point of a block (the
    #   graph's optional global_stride input, graph_rewrite.add_global_stride); 1 = all, exact
    clustering: str = "paper"   # one of CLUSTERINGS (PipelineConfig.clustering)
    fragment_eps: float = 0.006  # connected: DBSCAN eps in metres (sensor spacing, not part size)
    fragment_density: int = 20     # connected: DBSCAN min_samples in input points
    fragment_min_points: int = 300  # connected: smallest instance, input points
    fragment_join: float = 2.0     # connected: a center's pieces join within this diagonal (d_max)
    fragment_crease: float = 0.0   # connected, organized clouds: cut concave creases sharper than
    #   this curvature (1/m; fragments.concave_creases); 0 = off
    feature_names: tuple[str, ...] = FEATURE_NAMES
    description: str = ""
    trained_on: dict[str, Any] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)

    @property
    def uses_normals(self) -> bool:
        """Whether the network takes surface normals (features.surface_normals) as columns 6-8."""
        return self.feature_names == FEATURE_NAMES_WITH_NORMALS

    def to_json(self) -> dict[str, Any]:
        """The on-disk form, with the input/output description spelled out for humans."""
        body = asdict(self)
        body["feature_names"] = list(self.feature_names)
        return {
            "format": CARD_FORMAT,
            **body,
            "inputs": {
                "features": {
                    "dtype": "float32",
                    "shape": ["batch", "points", len(self.feature_names)],
                    "normalisation": "columns 0-2: xyz minus the block minimum, divided by "
                    "part_radius; columns 3-5: xyz minus the block minimum, divided by the "
                    "block extent per axis (0..1)" + (
                        "; columns 6-8: the unit surface normal of each point's 8 nearest "
                        "neighbours in the knn input (itself included), facing -z"
                        if self.uses_normals else "") +
                    ". Blocks are spatial tiles of at most "
                    "block_size points after voxel downsampling at voxel_factor * part_radius.",
                },
                "knn": {
                    "dtype": "int64",
                    "shape": ["batch", "points", self.k],
                    "meaning": "indices of neighbours in 3D within the block, the point itself "
                    "first (fpcc_ros.features.knn_graph): the k nearest, or when knn_reach > k "
                    "the knn_near nearest then k - knn_near spread evenly over the knn_reach "
                    "nearest",
                },
            },
            "outputs": {
                "embedding": {"dtype": "float32", "shape": ["batch", "points", self.embedding_dim]},
                "center_score": {"dtype": "float32", "shape": ["batch", "points"], "range": [0, 1]},
            },
        }

    def save(self, path: Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n")


def card_path_for(model_path: Path) -> Path:
    return Path(model_path).with_suffix(".json")


def load_card(path: Path) -> ModelCard:
    """Read and validate a card; every problem names the key, the value and the fix."""
    path = Path(path)
    if not path.is_file():
        raise ModelCardError(
            f"model card {path} not found: every .onnx model needs a card JSON with the same "
            "stem beside it (written by `fpcc export`)")
    try:
        raw = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelCardError(f"model card {path} is not readable JSON ({exc}); re-export the "
                             "model with `fpcc export`") from exc
    if not isinstance(raw, dict) or raw.get("format") != CARD_FORMAT:
        got = raw.get("format") if isinstance(raw, dict) else type(raw).__name__
        raise ModelCardError(f"model card {path}: 'format' is {got!r}, expected {CARD_FORMAT!r}; "
                             "re-export the model with `fpcc export`")
    known = {f for f in ModelCard.__dataclass_fields__}
    kwargs = {key: value for key, value in raw.items() if key in known}
    for required in ("name", "k", "part_radius"):
        if required not in kwargs:
            raise ModelCardError(f"model card {path}: missing key {required!r}")
    if "feature_names" in kwargs:
        kwargs["feature_names"] = tuple(kwargs["feature_names"])
    try:
        card = ModelCard(**kwargs)
    except TypeError as exc:
        raise ModelCardError(f"model card {path}: {exc}") from exc
    _check_values(card, path)
    return card


def _check_values(card: ModelCard, path: Path) -> None:
    checks = [
        ("k", card.k, isinstance(card.k, int) and card.k >= 1, "a positive integer"),
        ("part_radius", card.part_radius, _positive(card.part_radius), "a positive length in metres"),
        ("block_size", card.block_size, isinstance(card.block_size, int) and card.block_size >= card.k,
         "an integer >= k"),
        ("voxel_factor", card.voxel_factor, _number(card.voxel_factor) and card.voxel_factor >= 0,
         "a number >= 0"),
        ("screening_factor", card.screening_factor, _positive(card.screening_factor), "> 0"),
        ("score_threshold", card.score_threshold,
         _number(card.score_threshold) and 0 <= card.score_threshold < 1, "in [0, 1)"),
        ("feature_gate", card.feature_gate, _positive(card.feature_gate), "> 0"),
        ("center_merge", card.center_merge,
         _number(card.center_merge) and 0 <= card.center_merge <= 10, "between 0 (off) and 10"),
        ("center_prototype", card.center_prototype,
         _number(card.center_prototype) and 0 <= card.center_prototype <= 2,
         "between 0 (the center point's own embedding) and 2 part radii"),
        ("global_stride", card.global_stride,
         isinstance(card.global_stride, int) and not isinstance(card.global_stride, bool)
         and 1 <= card.global_stride <= MAX_GLOBAL_STRIDE,
         f"an integer from 1 (every point) to {MAX_GLOBAL_STRIDE}"),
        ("clustering", card.clustering, card.clustering in CLUSTERINGS,
         f"one of {list(CLUSTERINGS)}"),
        ("fragment_eps", card.fragment_eps,
         _number(card.fragment_eps) and 1e-4 <= card.fragment_eps <= 1.0,
         "a length in metres between 0.0001 and 1"),
        ("fragment_density", card.fragment_density,
         isinstance(card.fragment_density, int) and not isinstance(card.fragment_density, bool)
         and 1 <= card.fragment_density <= 10_000, "an integer from 1 to 10000 input points"),
        ("fragment_min_points", card.fragment_min_points,
         isinstance(card.fragment_min_points, int) and not isinstance(card.fragment_min_points, bool)
         and card.fragment_min_points >= 1, "an integer >= 1 (input points)"),
        ("fragment_join", card.fragment_join,
         _number(card.fragment_join) and 0 <= card.fragment_join <= 4, "between 0 and 4 part radii"),
        ("fragment_crease", card.fragment_crease,
         _number(card.fragment_crease) and 0 <= card.fragment_crease <= MAX_FRAGMENT_CREASE,
         f"a curvature in 1/m between 0 (off) and {MAX_FRAGMENT_CREASE:g}"),
        ("feature_names", card.feature_names,
         card.feature_names in (FEATURE_NAMES, FEATURE_NAMES_WITH_NORMALS),
         f"{list(FEATURE_NAMES)} or, for a model trained with normals, "
         f"{list(FEATURE_NAMES_WITH_NORMALS)} (this runtime's features)"),
    ]
    for key, value, ok, expected in checks:
        if not ok:
            raise ModelCardError(f"model card {path}: {key}={value!r} is invalid; expected {expected}")


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == value


def _positive(value: Any) -> bool:
    return _number(value) and value > 0
