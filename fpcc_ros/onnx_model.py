"""onnxruntime session for an exported FPCC-Net plus its model card.

Everything that can be wrong with a model file is found here, at load time, and reported as a
:class:`ModelLoadError` that says what to fix; the per-frame path then trusts the session.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import onnxruntime as ort

from fpcc_ros.model_card import ModelCard, ModelCardError, card_path_for, load_card
from fpcc_ros.weight_flush import WeightFlush, dead_channels, flush_tiny_weights

_log = logging.getLogger("fpcc_ros")

INPUTS = ("features", "knn")
OUTPUTS = ("embedding", "center_score")
# optional input (an initializer a run may override, default 1): the global feature's max over
# every s-th point of a block; graph_rewrite.add_global_stride adds it
STRIDE_INPUT = "global_stride"
DEFAULT_MODEL = Path(__file__).resolve().parent.parent / "models" / "fpcc_default.onnx"


class ModelLoadError(RuntimeError):
    """The model or its card cannot be used; the message says why and what to do."""


def default_model_path() -> Path:
    """The shipped model: beside the sources in a checkout, or in share/ after an install."""
    if DEFAULT_MODEL.is_file():
        return DEFAULT_MODEL
    try:
        from ament_index_python.packages import get_package_share_directory
        shared = Path(get_package_share_directory("fpcc_ros")) / "models" / DEFAULT_MODEL.name
        if shared.is_file():
            return shared
    except Exception:  # noqa: BLE001 - no ament index: fall back to the source path
        pass
    return DEFAULT_MODEL


class FpccModel:
    """A loaded FPCC-Net: ``run(features, knn) -> (embedding, center_score)``."""

    def __init__(self, path: Path | str, providers: list[str] | None = None, threads: int = 0):
        self.path = Path(path)
        self.threads = int(threads)
        if not self.path.is_file():
            raise ModelLoadError(f"model file {self.path} not found; set the 'model' parameter to "
                                 "an exported .onnx (see `fpcc export`) or leave it empty for the "
                                 "shipped default")
        try:
            self.card: ModelCard = load_card(card_path_for(self.path))
        except ModelCardError as exc:
            raise ModelLoadError(str(exc)) from exc
        # users bring models exported elsewhere: tiny weights (denormal floats and those whose
        # products are) cost Intel cores ~30x per product; zero them before the session sees them
        try:
            model_bytes, self.flush = flush_tiny_weights(self.path.read_bytes())
        except (OSError, ValueError) as exc:
            raise ModelLoadError(f"model file {self.path} is not a loadable ONNX model ({exc}); "
                                 "re-export it with `fpcc export`") from exc
        # dead channels (a weight row all ~0: the layer outputs a constant) mean a collapsed
        # network: slow for nothing and inaccurate; say so where users look (log, bench)
        self.dead_channels: dict[str, tuple[int, int]] = dead_channels(model_bytes)
        if self.flush.flushed:
            _log.warning("%s: %d of %d float weights were tiny (|w| < 1e-20; %d denormal) and are "
                         "set to 0 in memory (they slow Intel CPUs, not the outputs); "
                         "`scripts/optimize_onnx.py %s` fixes the file", self.path,
                         self.flush.flushed, self.flush.weights, self.flush.denormal, self.path)
        self.session = self._open_session(model_bytes, providers or ["CPUExecutionProvider"],
                                          threads)
        # exact graph rewrites applied by scripts/optimize_onnx.py (fpcc_ros.graph_rewrite)
        self.graph_notes: str = self.session.get_modelmeta().custom_metadata_map.get(
            "fpcc_graph", "")
        # the optional input of graph_rewrite.add_global_stride (onnxruntime lists it among
        # the initializers a run may override, not among the inputs)
        self.supports_global_stride: bool = STRIDE_INPUT in {
            i.name for i in self.session.get_overridable_initializers()}
        self._check_signature()
        self._check_run()

    def health_line(self) -> str:
        """``tiny weights ...; dead channels: W 892/1024 (87%), ...`` (or ``no dead channels``)."""
        dead = ", ".join(f"{name} {d}/{n} ({d / n:.0%})" for name, (d, n) in
                         sorted(self.dead_channels.items(), key=lambda kv: -kv[1][0] / kv[1][1]))
        return (f"{self.flush.flushed} tiny weights zeroed at load ({self.flush.denormal} "
                f"denormal); " + (f"dead channels: {dead}" if dead else "no dead channels"))

    @property
    def collapsed(self) -> bool:
        """A weight matrix with more than 10 % dead channels (model_health.py's limit)."""
        return any(d / n > 0.1 for d, n in self.dead_channels.values())

    @property
    def active_providers(self) -> list[str]:
        return self.session.get_providers()

    def _open_session(self, model_bytes: bytes, providers: list[str],
                      threads: int) -> ort.InferenceSession:
        available = ort.get_available_providers()
        missing = [p for p in providers if p not in available]
        if missing:
            raise ModelLoadError(f"providers={missing} are not available in this onnxruntime "
                                 f"build; available: {available}")
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.intra_op_num_threads = max(0, int(threads))
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        # Workers spin between the operators of a run (fast hand-offs) but stop when it ends:
        # left spinning they hold a core for ~25 ms after every run, which the kNN queries and
        # the node's DDS threads need on a 2-core machine.
        options.add_session_config_entry("session.force_spinning_stop", "1")
        # Not session.set_denormal_as_zero: it sets the calling thread's FTZ/DAZ flags for the
        # rest of the process, and scipy's cKDTree query then crashed (SIGSEGV in the baseline's
        # RANSAC after a pipeline run in the same process, 2026-12-03). Flushing the weights at
        # load is what removes the 30x cost (issue 25: 560 -> 37 ms, the flag alone -> 300 ms).
        try:
            return ort.InferenceSession(model_bytes, sess_options=options, providers=providers)
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises many unrelated types
            raise ModelLoadError(f"model file {self.path} is not a loadable ONNX model ({exc}); "
                                 "re-export it with `fpcc export`") from exc

    def _check_signature(self) -> None:
        inputs = {i.name: i for i in self.session.get_inputs()}
        outputs = {o.name: o for o in self.session.get_outputs()}
        problems = []
        if set(inputs) != set(INPUTS):
            problems.append(f"inputs are {sorted(inputs)}, expected {list(INPUTS)}")
        if not set(OUTPUTS) <= set(outputs):
            problems.append(f"outputs are {sorted(outputs)}, expected {list(OUTPUTS)}")
        if not problems:
            expected_last = {
                ("features", len(self.card.feature_names)),
                ("knn", self.card.k),
            }
            for name, dim in expected_last:
                shape = inputs[name].shape
                if len(shape) != 3 or (isinstance(shape[-1], int) and shape[-1] != dim):
                    problems.append(f"input {name!r} has shape {shape}, the card says "
                                    f"[batch, points, {dim}]")
            emb = outputs["embedding"].shape
            if len(emb) != 3 or (isinstance(emb[-1], int) and emb[-1] != self.card.embedding_dim):
                problems.append(f"output 'embedding' has shape {emb}, the card says "
                                f"[batch, points, {self.card.embedding_dim}]")
        if problems:
            raise ModelLoadError(f"{self.path} is not an FPCC-Net matching its card: "
                                 + "; ".join(problems) + ". Re-export with `fpcc export`.")

    def _check_run(self) -> None:
        """One inference on a small synthetic block, checked against the card.

        The signature check cannot see symbolic dimensions (an export with a dynamic k or
        embedding size passes it whatever the card says), nor a graph that fails only when run;
        without this, such a model would start and then fail every frame.
        """
        from fpcc_ros.features import block_inputs

        card, n = self.card, max(4 * self.card.k, 64)
        xyz = np.random.default_rng(0).uniform(0.0, 4.0 * card.part_radius, (n, 3))
        features, knn = block_inputs(xyz, card.part_radius, card.k, card.uses_normals)
        features, knn = features[None], knn[None]
        try:
            embedding, score = self.run(features, knn)
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises many unrelated types
            raise ModelLoadError(
                f"{self.path}: a test inference on {n} points with the card's k={card.k} failed "
                f"({exc}); the model and its card {card_path_for(self.path)} disagree. Re-export "
                "with `fpcc export`.") from exc
        problems = []
        if np.shape(embedding) != (1, n, card.embedding_dim):
            problems.append(f"'embedding' came out {list(np.shape(embedding))}, the card says "
                            f"[1, {n}, {card.embedding_dim}]")
        if np.shape(score) != (1, n):
            problems.append(f"'center_score' came out {list(np.shape(score))}, expected [1, {n}]")
        elif not (np.isfinite(score).all() and score.min() >= 0.0 and score.max() <= 1.0):
            problems.append("'center_score' is not in [0, 1] (a score head without its sigmoid?)")
        if not problems and not np.isfinite(embedding).all():
            problems.append("'embedding' has NaN/Inf values")
        if problems:
            raise ModelLoadError(f"{self.path} does not behave as its card "
                                 f"{card_path_for(self.path)} says: " + "; ".join(problems)
                                 + ". Re-export with `fpcc export`.")

    def run(self, features: np.ndarray, knn: np.ndarray,
            global_stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """One block (or a batch of equal-sized blocks): (B,N,6), (B,N,K) -> (B,N,128), (B,N).

        ``global_stride`` > 1 takes the global feature's max over every s-th point (a model
        whose graph has the input: :attr:`supports_global_stride`)."""
        feed = {"features": features, "knn": knn}
        if global_stride != 1:
            if not self.supports_global_stride:
                raise ValueError(f"global_stride={global_stride}: {self.path} has no "
                                 f"'{STRIDE_INPUT}' input; run scripts/optimize_onnx.py on it, "
                                 "or use global_stride 1")
            feed[STRIDE_INPUT] = np.array([global_stride], dtype=np.int64)
        embedding, score = self.session.run(list(OUTPUTS), feed)
        return embedding, score
