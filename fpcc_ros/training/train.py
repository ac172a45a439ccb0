"""Train FPCC-Net on scene NPZ files: AdamW, cosine learning rate, checkpoints, validation.

A run directory holds ``checkpoint_last.pt`` (written every epoch and when ``time_limit_min``
stops the run mid-epoch), ``checkpoint_best.pt``, ``history.csv`` and ``history.png``.
Checkpoints hold only tensors and plain Python values, so they load with
``torch.load(weights_only=True)``; batches are seeded by (seed, epoch), so a resumed run continues
exactly where it stopped, mid-epoch included.

Validation runs the model on every block of each validation scene, gathers the embedding and
center score per downsampled point and hands them to a ``postprocess`` callable that returns a
label per scene point: by default the runtime's own clustering (``runtime_postprocess``), scored
with fpcc_ros.metrics.
"""
from __future__ import annotations

import csv
import math
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from fpcc_ros.features import feature_names
from fpcc_ros.onnx_model import default_model_path
from fpcc_ros.training.dataset import BlockDataset, DataConfig, Scene, collate, find_scenes, \
    load_scene, scene_blocks
from fpcc_ros.training.health import WARN_DEAD_SHARE, channel_health, dead_layers, \
    gradient_norm, health_line, make_optimizer
from fpcc_ros.training.loss import EPS1, EPS2, batch_loss, distill_loss, nearest_prototype_hits
from fpcc_ros.training.model import FPCCNet, NetConfig, with_normal_inputs

CHECKPOINT_FORMAT = "fpcc_ros/checkpoint/1"
_now = time.monotonic  # the run's clock (tests replace it)
HISTORY_FIELDS = ("epoch", "lr", "loss", "loss_ef", "loss_cs", "loss_kd", "val_loss",
                  "val_loss_ef", "val_loss_cs", "val_center_mae", "val_nearest_own",
                  "val_precision", "val_recall", "val_mucov", "val_precision_paper",
                  "val_recall_paper", "grad_norm", "seconds")
LIVE_PREFIX = "live_"   # history columns live_<layer>: live channels of that layer (health.py)


# Weight of the center-score loss in training. The paper's alpha = 3 goes with its L_EF, a plain
# sum over pairs; ours is a mean over valid pairs (see loss.py), and with alpha = 3 the center term
# made up ~85 % of the loss late in training (per-part gear shaft: L_EF 0.008, 3 L_CS 0.052).
# With alpha = 1 the same 30-minute per-part fine-tune reached gear-shaft validation F1 0.675
# instead of 0.576 (24 piles, each calibrated on the same grid) and test P/R 0.729/0.599 instead
# of 0.622/0.524, with the same center loss (validation L_CS 0.0168 both).
TRAIN_ALPHA = 1.0


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 30
    lr: float = 1e-3
    min_lr_fraction: float = 0.01
    weight_decay: float = 1e-4  # decoupled (AdamW), weight matrices only: see health.make_optimizer
    batch: int = 4
    alpha: float = TRAIN_ALPHA
    eps1: float = EPS1
    eps2: float = EPS2
    prototype: float = 0.0      # weight of loss.prototype_loss (0 = the paper's loss only)
    augment: bool = True
    seed: int = 0
    threads: int = 2
    time_limit_min: float = 0.0
    anneal_by_time: bool = False  # the cosine ends by time_limit_min if the epochs would not fit
    val_every: int = 1          # validate after every n-th epoch, and after the run's last
    score_threshold: float = 0.6
    screening_factor: float = 1.0
    feature_gate: float = 1.0
    min_points: int = 50
    precision: str = "auto"     # see resolve_precision
    teacher: str = ""           # weights whose outputs the net also learns to match (distillation)
    distill: float = 1.0        # weight of that term (loss.distill_loss) when there is a teacher
    data: DataConfig = DataConfig()
    net: NetConfig = NetConfig()

    def to_dict(self) -> dict[str, Any]:
        body = {k: v for k, v in asdict(self).items() if k not in ("data", "net")}
        body["data"] = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self.data).items()}
        body["net"] = self.net.to_dict()
        return body

    @classmethod
    def from_dict(cls, body: dict[str, Any]) -> "TrainConfig":
        body = dict(body)
        data = DataConfig.from_dict(body.pop("data", {}))
        net = NetConfig.from_dict(body.pop("net", {}))
        body.setdefault("precision", "fp32")   # runs from before the option trained in fp32
        known = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in body.items() if k in known}, data=data, net=net)


@dataclass
class ScenePrediction:
    """Network outputs for one scene: per downsampled point (rows of ``xyz``, which are scene rows
    ``rep``), and ``inverse`` mapping every scene point to its downsampled row."""

    rep: np.ndarray
    inverse: np.ndarray
    xyz: np.ndarray
    embedding: np.ndarray
    center_score: np.ndarray
    model: Any = None          # the network that made it, for postprocessing that reruns it


Postprocess = Callable[[Scene, ScenePrediction, TrainConfig], np.ndarray]


PRECISIONS = ("auto", "fp32", "bf16")


def resolve_precision(precision: str) -> str:
    """'fp32' or 'bf16' (autocast of the network's forward pass; weights, optimizer and loss stay
    fp32). 'auto' is bf16 where the CPU computes it natively (AVX512-BF16 or AMX), else fp32:
    emulated bf16 is slower than fp32.

    Measured on this project's 2-core EPYC (AVX512-BF16): 100 fine-tuning steps of the full net
    took 28 s instead of 43 s, and the validation loss after them was 0.06143 against 0.06139.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r} is not one of {', '.join(PRECISIONS)}")
    if precision != "auto":
        return precision
    native = getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)() or \
        getattr(torch.cpu, "_is_amx_tile_supported", lambda: False)()
    return "bf16" if native else "fp32"


# ----------------------------------------------------------------------------- checkpoints

def lr_at(config: TrainConfig, epoch: float, elapsed_s: float = 0.0) -> float:
    """Cosine decay from lr to lr * min_lr_fraction over the configured epochs or, with
    ``anneal_by_time`` and a time limit, over whichever of the two ends first (``elapsed_s``:
    this run's seconds so far). ``epoch`` may be fractional (within an epoch).

    A fixed-budget fine-tune (the per-part recipe: 30 minutes) that the clock stops would
    otherwise end at a high learning rate in the middle of its schedule: on the ring screw, 21
    of 25 epochs fit in 30 minutes. Off by default: a run cut by its time limit to be resumed
    later (the default model's, across sessions) resumes exactly only on an epoch schedule.
    """
    frac = epoch / max(config.epochs, 1)
    if config.anneal_by_time and config.time_limit_min > 0:
        frac = max(frac, elapsed_s / (60.0 * config.time_limit_min))
    frac = min(frac, 1.0)
    low = config.lr * config.min_lr_fraction
    return low + 0.5 * (config.lr - low) * (1 + math.cos(math.pi * frac))


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint or weights file (tensors and plain values only)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} not found")
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "model" not in state:
        raise ValueError(f"{path} is not an fpcc_ros checkpoint (no 'model' entry); use a "
                         "checkpoint_*.pt from `fpcc train` or the .pt written beside an exported model")
    return state


def model_from_checkpoint(state: dict[str, Any]) -> FPCCNet:
    model = FPCCNet(NetConfig.from_dict(state.get("net", {})))
    model.load_state_dict(state["model"])
    return model


def resolve_init(init: str | Path) -> Path:
    """The .pt an ``--init`` names: a .pt itself, the .pt beside an .onnx/.json model, or
    ``default`` (the shipped model's weights, beside its ONNX in a checkout or an install)."""
    if str(init) == "default":
        pt = default_model_path().with_suffix(".pt")
        if not pt.is_file():
            raise FileNotFoundError(f"--init default: the shipped weights {pt} are missing; "
                                    "reinstall fpcc_ros, or pass --init PATH.pt")
        return pt
    path = Path(init)
    if path.suffix in (".onnx", ".json"):
        pt = path.with_suffix(".pt")
        if not pt.is_file():
            raise FileNotFoundError(f"--init {path}: no torch weights {pt} beside it; `fpcc export` "
                                    "writes them, ONNX weights cannot be trained further")
        return pt
    return path


# What the network's inputs are built with: fine-tuning must keep them, or the weights meet
# neighbourhoods and densities they were never trained on
GRAPH_FIELDS = ("k", "block_size", "voxel_factor", "knn_near", "knn_reach", "normals")


def data_config_for(init: str | Path | None, **explicit: Any) -> DataConfig:
    """The data settings of a run: the ``explicit`` ones (None = not given), the rest from the
    ``init`` weights' training run when there are any, else :class:`DataConfig`'s defaults (the
    shipped model's). An explicit graph setting that differs from the init weights' is a warning,
    not an error: retraining to a new graph from old weights is legitimate, just slower."""
    init_path = resolve_init(init) if init is not None else None
    base = (_trained_data(load_checkpoint(init_path)) if init_path is not None else None) \
        or DataConfig()
    given = {name: value for name, value in explicit.items() if value is not None}
    for name in GRAPH_FIELDS:
        if init_path is not None and name in given and given[name] != getattr(base, name):
            print(f"fpcc train: --{name.replace('_', '-')} {given[name]} differs from the --init "
                  f"weights' {getattr(base, name)}; the network will have to relearn its inputs "
                  f"(leave it out to keep the init's)", file=sys.stderr)
    return replace(base, **given)


def _trained_data(state: dict[str, Any]) -> DataConfig | None:
    """The data settings a checkpoint's weights were trained with (None: not recorded)."""
    saved = state.get("config", {}).get("data")
    return DataConfig.from_dict(saved) if saved else None


def _plain(value: Any) -> Any:
    """numpy scalars -> Python numbers, recursively (weights_only checkpoints need plain types)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


# ----------------------------------------------------------------------------- validation

@torch.no_grad()
def predict_scene(model: FPCCNet, scene: Scene, data: DataConfig,
                  on_block: Callable[[dict, torch.Tensor, torch.Tensor], None] | None = None) -> ScenePrediction:
    """Run the model on every block of a scene (no augmentation), as the runtime does.
    ``on_block(batch, embedding, center_score)`` sees each block that holds part points."""
    model.eval()
    cut = scene_blocks(scene, data, rng=None, skip_empty=False)
    n = len(cut.rep)
    embedding = np.zeros((n, model.config.embedding_dim), np.float32)
    score = np.zeros(n, np.float32)
    for block in cut.blocks:
        batch = collate([block])
        emb, s = model(batch["features"], batch["knn"])
        embedding[block.index], score[block.index] = emb[0].numpy(), s[0].numpy()
        if on_block is not None and (block.instance > 0).any():
            on_block(batch, emb, s)
    return ScenePrediction(cut.rep, cut.inverse, scene.xyz[cut.rep], embedding, score, model)


class TorchBlockModel:
    """The torch network behind the runtime model interface (``card`` + ``run``), so validation
    runs the node's own :class:`fpcc_ros.pipeline.Pipeline` (voxels, floor removal, blocks with
    halos, NMS, clustering, min_points) on exactly what the exported ONNX would compute."""

    def __init__(self, net: FPCCNet, config: "TrainConfig"):
        from fpcc_ros.model_card import ModelCard
        self.net = net
        self.card = ModelCard(name="validation", k=config.data.k, part_radius=1.0,
                              knn_near=config.data.knn_near, knn_reach=config.data.knn_reach,
                              block_size=config.data.block_size,
                              voxel_factor=config.data.voxel_factor,
                              embedding_dim=net.config.embedding_dim,
                              feature_names=feature_names(net.config.normals))

    @torch.no_grad()
    def run(self, features: np.ndarray, knn: np.ndarray,
            global_stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        if global_stride != 1:   # validation runs the network as trained: every point
            raise ValueError(f"global_stride={global_stride}: the torch network pools every point")
        self.net.eval()
        emb, score = self.net(torch.from_numpy(features), torch.from_numpy(knn))
        return emb.numpy(), score.numpy()


def runtime_postprocess(scene: Scene, pred: ScenePrediction, config: TrainConfig) -> np.ndarray:
    """Labels per scene point from the runtime Pipeline itself, run on the prediction's network."""
    from fpcc_ros.pipeline import Pipeline, PipelineConfig

    runtime = PipelineConfig(part_radius=scene.part_radius, screening_factor=config.screening_factor,
                             score_threshold=config.score_threshold, feature_gate=config.feature_gate,
                             voxel_factor=config.data.voxel_factor, block_size=config.data.block_size,
                             min_points=config.min_points, remove_floor=config.data.remove_floor,
                             view_axis="+z")  # training scenes are in the camera frame
    pipeline = Pipeline(TorchBlockModel(pred.model, config), runtime)
    return pipeline.segment(scene.xyz).labels.astype(np.int32)


@torch.no_grad()
def validate(model: FPCCNet, scenes: Sequence[Scene], config: TrainConfig,
             postprocess: Postprocess | None = runtime_postprocess) -> dict[str, float]:
    """Validation loss on unaugmented blocks, center-score MAE per downsampled point and, with
    ``postprocess``, precision / recall / MUCov at IoU 0.5 summed over the scenes
    (fpcc_ros.metrics; ``val_precision``/``val_recall`` use the visible protocol, ``*_paper``
    count every ground-truth instance), and ``val_nearest_own``: the share of part points nearer
    their own part's center prototype than any other's (loss.nearest_prototype_hits), the
    embeddings' quality without clustering settings."""
    from fpcc_ros.metrics import InstanceCounts, scene_counts, visible_threshold

    model.eval()
    losses, abs_err, n_pts = [], 0.0, 0
    hits = [0, 0]
    visible, paper = InstanceCounts(), InstanceCounts()

    def block_loss(batch: dict, emb: torch.Tensor, s: torch.Tensor) -> None:
        losses.append([t.item() for t in batch_loss(emb, s, batch, config.alpha, config.eps1, config.eps2,
                                                     config.prototype)])
        for b, rows in enumerate(batch["valid"]):
            found = nearest_prototype_hits(emb[b][rows].float(), batch["instance"][b][rows],
                                           batch["center_score"][b][rows])
            hits[0], hits[1] = hits[0] + found[0], hits[1] + found[1]

    for scene in scenes:
        pred = predict_scene(model, scene, config.data, on_block=block_loss)
        abs_err += float(np.abs(pred.center_score - scene.center_score[pred.rep]).sum())
        n_pts += len(pred.rep)
        if postprocess is not None:
            labels = postprocess(scene, pred, config)
            visible += scene_counts(labels, scene.instance, "visible",
                                    visible_threshold(scene.num_pixels))
            paper += scene_counts(labels, scene.instance, "paper")
    out: dict[str, float] = {}
    if losses:
        out["val_loss"], out["val_loss_ef"], out["val_loss_cs"] = map(float, np.mean(losses, axis=0))
    if n_pts:
        out["val_center_mae"] = abs_err / n_pts
    if hits[1]:
        out["val_nearest_own"] = hits[0] / hits[1]
    if postprocess is not None and scenes:
        out.update(val_precision=visible.precision, val_recall=visible.recall, val_mucov=visible.mucov,
                   val_precision_paper=paper.precision, val_recall_paper=paper.recall)
    return out


# ----------------------------------------------------------------------------- history

def write_history(run_dir: Path, history: list[dict[str, Any]],
                  widths: dict[str, int] | None = None) -> None:
    """history.csv and history.png (losses, validation metrics and live channels per epoch;
    ``widths``: channels per layer, for the live share)."""
    live = sorted({k for h in history for k in h if k.startswith(LIVE_PREFIX)},
                  key=lambda k: next(i for i, h in enumerate(history) if k in h))
    with open(run_dir / "history.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=HISTORY_FIELDS + tuple(live), extrasaction="ignore")
        writer.writeheader()
        writer.writerows(history)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(15, 4))
    epochs = [h["epoch"] for h in history]
    for key in ("loss", "loss_ef", "loss_cs", "val_loss"):
        if any(key in h for h in history):
            ax1.plot(epochs, [h.get(key, np.nan) for h in history], marker=".", label=key)
    ax1.set_xlabel("epoch"), ax1.set_ylabel("loss")
    for key in ("val_precision", "val_recall", "val_nearest_own", "val_center_mae"):
        if any(key in h for h in history):
            ax2.plot(epochs, [h.get(key, np.nan) for h in history], marker=".", label=key)
    ax2.set_xlabel("epoch"), ax2.set_ylim(0, 1)
    # live share per layer: a collapsing network shows here long before its metrics stall
    widths = widths or {}
    for key in live:
        name = key[len(LIVE_PREFIX):]
        total = widths.get(name) or max(h.get(key, 0) for h in history) or 1
        ax3.plot(epochs, [h.get(key, np.nan) / total for h in history], marker=".", label=name)
    ax3.set_xlabel("epoch"), ax3.set_ylabel("live channels (share of the layer)"), ax3.set_ylim(0, 1.05)
    for ax in (ax1, ax2, ax3):
        if ax.get_lines():
            ax.legend()
    fig.tight_layout()
    fig.savefig(run_dir / "history.png", dpi=80)
    plt.close(fig)


def _validate_after(config: TrainConfig, epochs_done: int, out_of_time: bool) -> bool:
    """Validation after this epoch: every ``val_every``-th, and the run's last (its epochs
    done, or its time limit reached). Validating 12 piles costs ~15 s, about a tenth of a
    100-scene epoch; a fixed-budget fine-tune that ships its last checkpoint spends that on
    training instead."""
    return epochs_done % config.val_every == 0 or epochs_done >= config.epochs or out_of_time


def _score(row: dict[str, Any]) -> float:
    """Higher is better: validation F1 when measured, else minus a loss."""
    if "val_precision" in row:
        p, r = row["val_precision"], row["val_recall"]
        return 2 * p * r / (p + r) if p + r else 0.0
    return -row.get("val_loss", row["loss"])


# ----------------------------------------------------------------------------- training

def train(config: TrainConfig, data: Sequence[str | Path] | None, run_dir: str | Path,
          val: Sequence[str | Path] = (), init: str | Path | None = None, resume: bool = False,
          postprocess: Postprocess | None = runtime_postprocess, progress: bool = True,
          command: Sequence[str] | None = None) -> dict[str, Any]:
    """Train (or resume) a run; returns a summary: status ('done' or 'time_limit'), epochs done,
    last history row and the checkpoint paths.

    ``resume`` continues ``run_dir/checkpoint_last.pt`` with its saved configuration (only
    ``epochs``, ``time_limit_min``, ``anneal_by_time``, ``threads`` and ``val_every`` come from
    ``config``) and, when ``data`` / ``val`` are empty, its saved scene folders. ``init`` (ignored when resuming) names starting weights
    (see ``resolve_init``); the network widths then follow the init weights."""
    from tqdm import tqdm

    start_time = _now()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    last_path, best_path = run_dir / "checkpoint_last.pt", run_dir / "checkpoint_best.pt"
    state: dict[str, Any] | None = None
    if resume:
        if not last_path.is_file():
            raise FileNotFoundError(f"--resume: {last_path} not found; start without --resume")
        state = load_checkpoint(last_path)
        data = data or state["trained_on"]["data"]
        val = val or state["trained_on"]["validation"]
        saved = TrainConfig.from_dict(state["config"])
        config = replace(saved, epochs=config.epochs, time_limit_min=config.time_limit_min,
                         anneal_by_time=config.anneal_by_time, threads=config.threads,
                         val_every=config.val_every)
    config = replace(config, precision=resolve_precision(config.precision))
    if config.val_every < 1:
        raise ValueError(f"--val-every {config.val_every}: must be >= 1 (validate after every "
                         "N-th epoch and after the last); leave out --val for no validation")
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)

    init_state = None
    if state is None and init is not None:
        init_state = load_checkpoint(resolve_init(init))
        config = replace(config, net=NetConfig.from_dict(init_state.get("net", {})))
    elif state is None:   # from scratch: the inputs the data settings ask for
        config = replace(config, net=replace(
            config.net, in_features=len(feature_names(config.data.normals))))
    model = FPCCNet(config.net)
    if init_state is not None:
        model.load_state_dict(init_state["model"])
        if config.data.normals and not model.config.normals:   # --normals on 6-input weights
            model = with_normal_inputs(model)
            config = replace(config, net=model.config)
    if model.config.normals != config.data.normals:
        raise ValueError(f"the network {'takes' if model.config.normals else 'does not take'} "
                         f"surface normals but the data settings say normals="
                         f"{config.data.normals}; leave --normals to the --init weights")
    teacher = load_teacher(config.teacher, config.net, config.data) if config.teacher else None
    optimizer = make_optimizer(model, config.lr, config.weight_decay)

    if not data:
        raise ValueError("no training data: pass --data with folders of scene NPZ files")
    train_paths, val_paths = find_scenes(data), find_scenes(val) if val else []
    dataset = BlockDataset(train_paths, config.data, augment=config.augment, seed=config.seed)
    val_scenes = [load_scene(p) for p in val_paths]
    radii = sorted({s.part_radius for s in dataset.scenes})
    trained_on = {"data": [str(d) for d in data], "validation": [str(v) for v in val],
                  "part_names": sorted({s.part_name for s in dataset.scenes if s.part_name}),
                  "num_scenes": len(train_paths), "num_val_scenes": len(val_paths),
                  "part_radius": float(np.median([s.part_radius for s in dataset.scenes])),
                  "part_radii": radii[:20]}

    epoch, skip, history, best = 0, 0, [], -math.inf
    sums = _zero_sums(teacher is not None)
    wall_before = 0.0
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        epoch, skip, history = state["epoch"], state["step"], list(state["history"])
        sums, best, wall_before = dict(state["partial"]), state["best_score"], state["wall_time_s"]
        torch.set_rng_state(state["torch_rng"])
    command = list(command) if command is not None else list(sys.argv)

    def save(path: Path, step: int) -> None:
        tmp = path.with_suffix(".tmp")  # write then rename: a killed run never leaves half a file
        torch.save(_plain_state(model, optimizer, config, epoch, step, sums, history, best,
                                trained_on, command, wall_before + _now() - start_time), tmp)
        tmp.replace(path)

    def out_of_time() -> bool:
        return config.time_limit_min > 0 and _now() - start_time > 60 * config.time_limit_min

    status = "done"
    while epoch < config.epochs:
        epoch_start = _now()
        groups = dataset.batches(epoch, config.batch)
        lr = lr_at(config, epoch, _now() - start_time)   # the row's value if no step runs
        model.train()
        bar = tqdm(groups, desc=f"epoch {epoch + 1}/{config.epochs}", disable=not progress,
                   initial=skip, total=len(groups), leave=False)
        for step in range(skip, len(groups)):
            if out_of_time():
                status = "time_limit"
                save(last_path, step)
                bar.close()
                break
            lr = lr_at(config, epoch + step / len(groups), _now() - start_time)
            for group in optimizer.param_groups:
                group["lr"] = lr
            batch = collate(groups[step])
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=config.precision == "bf16"):
                embedding, score = model(batch["features"], batch["knn"])
                if teacher is not None:
                    with torch.no_grad():
                        target_embedding, target_score = teacher(batch["features"], batch["knn"])
            loss, loss_ef, loss_cs = batch_loss(embedding.float(), score.float(), batch,
                                                config.alpha, config.eps1, config.eps2,
                                                config.prototype)
            terms = {"loss_ef": loss_ef, "loss_cs": loss_cs}
            if teacher is not None:
                terms["loss_kd"] = distill_loss(embedding.float(), score.float(),
                                                target_embedding.float(), target_score.float(),
                                                batch["valid"])
                loss = loss + config.distill * terms["loss_kd"]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            sums["grad_norm"] += gradient_norm(model)
            optimizer.step()
            for key, value in {"loss": loss, **terms}.items():
                sums[key] += value.item()
            sums["steps"] += 1
            bar.update(1)
            bar.set_postfix(loss=f"{sums['loss'] / sums['steps']:.4f}")
        else:
            bar.close()
        if status == "time_limit":
            break
        steps = max(sums["steps"], 1)
        row = {"epoch": epoch + 1, "lr": lr, **{k: v / steps for k, v in sums.items() if k != "steps"}}
        health = channel_health(model)
        row.update({LIVE_PREFIX + name: live for name, (live, _) in health.items()})
        _warn_if_dying(health, epoch + 1)
        validating = bool(val_scenes) and _validate_after(config, epoch + 1, out_of_time())
        if validating:
            try:
                row.update(validate(model, val_scenes, config, postprocess))
            except Exception as exc:  # noqa: BLE001 - an epoch of training is worth more
                print(f"validation failed after epoch {epoch + 1} ({type(exc).__name__}: {exc}); "
                      "saving the checkpoint without validation metrics", file=sys.stderr)
        row["seconds"] = _now() - epoch_start
        history.append(_plain(row))
        write_history(run_dir, history, {name: total for name, (_, total) in health.items()})
        epoch, skip = epoch + 1, 0
        sums = _zero_sums(teacher is not None)
        # the best checkpoint is ranked among validated epochs when there is validation
        improved = (validating or not val_scenes) and _score(row) > best
        best = max(best, _score(row)) if improved else best
        save(last_path, 0)
        if improved:
            save(best_path, 0)
        if progress:
            print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()),
                  file=sys.stderr)
        if out_of_time() and epoch < config.epochs:
            status = "time_limit"
            break
    return {"status": status, "epochs_done": epoch, "precision": config.precision,
            "last": history[-1] if history else None,
            "checkpoint_last": str(last_path), "checkpoint_best": str(best_path),
            "wall_time_s": wall_before + _now() - start_time}


def _zero_sums(distilling: bool) -> dict[str, float]:
    """The running sums of an epoch's loss terms."""
    keys = ("loss", "loss_ef", "loss_cs", "grad_norm") + (("loss_kd",) if distilling else ())
    return {**dict.fromkeys(keys, 0.0), "steps": 0}


def _warn_if_dying(health: dict[str, tuple[int, int]], epoch: int) -> None:
    """A loud warning when a layer has lost more than WARN_DEAD_SHARE of its channels: they do
    not come back (no gradient reaches a channel whose scale is ~0), so stop and fix the run."""
    dying = dead_layers(health, WARN_DEAD_SHARE)
    if dying:
        worst = ", ".join(f"{name} {share:.0%} dead" for name, share in dying.items())
        print(f"\nWARNING fpcc train: after epoch {epoch} {worst} (more than "
              f"{WARN_DEAD_SHARE:.0%} of the layer's channels output a constant; dead channels "
              "never recover). Check --weight-decay, --lr and --precision before training on; "
              f"live channels: {health_line(health)}\n", file=sys.stderr)


def load_teacher(teacher: str | Path, net: NetConfig, data: DataConfig) -> FPCCNet:
    """The frozen network a student learns to match (see loss.distill_loss): an ``--init``-style
    name (a .pt, the .pt beside an .onnx, or 'default'). Its embedding must have the student's
    width, since the student copies it value for value, and it must have been trained on the
    run's graph: on other neighbourhoods its outputs are no target."""
    state = load_checkpoint(resolve_init(teacher))
    model = model_from_checkpoint(state).eval()
    if model.config.embedding_dim != net.embedding_dim:
        raise ValueError(f"--teacher {teacher}: its embedding has {model.config.embedding_dim} "
                         f"dimensions, the trained net's {net.embedding_dim}; distil only between "
                         "nets of one embedding width (scripts/slice_net.py keeps it)")
    theirs = _trained_data(state)
    if theirs is not None:
        differ = [f"{name} {getattr(theirs, name)} (the run: {getattr(data, name)})"
                  for name in GRAPH_FIELDS if getattr(theirs, name) != getattr(data, name)]
        if differ:
            raise ValueError(f"--teacher {teacher} was trained with {', '.join(differ)}; "
                             "train the student with the teacher's graph settings (leave them "
                             "unset with --init, or pass the teacher's)")
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    return model


def _plain_state(model: FPCCNet, optimizer: torch.optim.Optimizer, config: TrainConfig, epoch: int,
                 step: int, sums: dict, history: list, best: float, trained_on: dict,
                 command: list[str], wall_time_s: float) -> dict[str, Any]:
    return {
        "format": CHECKPOINT_FORMAT,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "net": model.config.to_dict(),
        "config": config.to_dict(),
        "epoch": int(epoch),
        "step": int(step),
        "partial": _plain(sums),
        "history": _plain(history),
        "best_score": float(best),
        "trained_on": _plain(trained_on),
        "command": [str(c) for c in command],
        "wall_time_s": float(wall_time_s),
        "torch_rng": torch.get_rng_state(),
    }
