"""Training blocks from scene NPZ files, cut exactly as the runtime cuts them.

Scene -> finite points -> voxel downsample at voxel_factor * part_radius -> spatial blocks of at
most block_size points -> (block_inputs: features and kNN graph) per block, all from fpcc_ros.features, so
the network trains on what it will see. Labels follow each voxel's representative point.

Augmentation (training only): a random rotation about the camera z axis (the viewing axis, so
the pile still looks like a depth camera's view), a small scale jitter of the points with the
part radius kept (robustness to a mis-set part_radius), a jittered voxel size and random dropout
of downsampled points (sparser or denser clouds than the default). Everything is numpy; loaded
scenes and unaugmented blocks are cached, augmented blocks are rebuilt per epoch from the cache
with a generator seeded by (seed, epoch, scene), so a resumed run sees the same data.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import torch

from fpcc_ros.features import (block_inputs, dominant_plane, plane_tolerance,
                               spatial_blocks, voxel_downsample)


@dataclass(frozen=True)
class DataConfig:
    k: int = 16
    block_size: int = 2048
    voxel_factor: float = 0.1
    voxel_jitter: tuple[float, float] = (0.8, 1.25)
    scale_jitter: tuple[float, float] = (0.9, 1.1)
    max_dropout: float = 0.15
    rotate: bool = True
    remove_floor: bool = True   # as the runtime pipeline does (fpcc_ros.pipeline step 2b)
    knn_near: int = 8           # dilated neighbourhood (features.neighbour_columns); 0 = plain
    knn_reach: int = 48
    normals: bool = False       # surface normals as three more input columns (fpcc train --normals)

    @classmethod
    def from_dict(cls, body: dict[str, Any]) -> "DataConfig":
        """From a checkpoint's saved settings. Runs saved before the dilated graph existed used
        plain kNN, whatever today's defaults are; keys this version does not know are ignored."""
        known = set(cls.__dataclass_fields__)
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in body.items() if k in known}
        values.setdefault("knn_near", 0)
        values.setdefault("knn_reach", 0)
        return cls(**values)


@dataclass
class Scene:
    """The finite points of one scene NPZ and their ground truth."""

    name: str
    xyz: np.ndarray            # (n, 3) float32, metres
    instance: np.ndarray       # (n,) int32, 0 = background
    center_score: np.ndarray   # (n,) float32 in [0, 1]
    part_radius: float
    part_name: str = ""
    num_pixels: int = 0        # points in the file, NaN included (sensor resolution)


@dataclass
class Block:
    """One network input. ``index`` maps rows to the points the block was cut from."""

    features: np.ndarray       # (n, 6) float32, (n, 9) with normals
    knn: np.ndarray            # (n, k) int64
    xyz: np.ndarray            # (n, 3) float32
    instance: np.ndarray       # (n,) int64
    center_score: np.ndarray   # (n,) float32
    part_radius: float
    index: np.ndarray          # (n,) int64


@dataclass
class SceneBlocks:
    """A scene cut into blocks. ``rep`` are the scene rows the blocks were cut from (voxel
    representatives, after dropout); ``inverse`` maps every scene row to its row of ``rep``
    (only without augmentation, where no representative is dropped)."""

    rep: np.ndarray
    inverse: np.ndarray | None
    blocks: list[Block]


def load_scene(path: str | Path) -> Scene:
    """Read a scene NPZ (DESIGN.md section 4) and keep its finite points."""
    path = Path(path)
    with np.load(path, allow_pickle=False) as npz:
        for key in ("points", "instance", "center_score", "part_radius"):
            if key not in npz:
                raise ValueError(f"scene {path}: missing array {key!r}; scene NPZ files need "
                                 "points, instance, center_score and part_radius")
        points = np.asarray(npz["points"], dtype=np.float32)
        instance = np.asarray(npz["instance"])
        score = np.asarray(npz["center_score"], dtype=np.float32)
        part_radius = float(f"{float(np.asarray(npz['part_radius'])):.7g}")  # float32 -> 7 digits
        part_name = str(np.asarray(npz["part_name"])) if "part_name" in npz else ""
    if points.ndim not in (2, 3) or points.shape[-1] != 3:
        raise ValueError(f"scene {path}: points has shape {points.shape}; expected (N, 3) or (H, W, 3)")
    lead = points.shape[:-1]
    for key, arr in (("instance", instance), ("center_score", score)):
        if arr.shape != lead:
            raise ValueError(f"scene {path}: {key} has shape {arr.shape}; expected {lead} "
                             "(the leading shape of points)")
    if not part_radius > 0:
        raise ValueError(f"scene {path}: part_radius={part_radius}; expected a positive length in m")
    xyz = points.reshape(-1, 3)
    finite = np.isfinite(xyz).all(axis=1)
    return Scene(name=path.stem, xyz=xyz[finite], instance=instance.reshape(-1)[finite].astype(np.int32),
                 center_score=score.reshape(-1)[finite], part_radius=part_radius, part_name=part_name,
                 num_pixels=int(np.prod(lead)))


def find_scenes(dirs: Sequence[str | Path]) -> list[Path]:
    """All *.npz under the given directories (or the files themselves), sorted."""
    found: list[Path] = []
    for d in dirs:
        d = Path(d)
        if d.is_file():
            found.append(d)
        elif d.is_dir():
            found.extend(sorted(d.rglob("*.npz")))
        else:
            raise FileNotFoundError(f"scene directory {d} does not exist; pass a folder of scene NPZ files")
    return found


def blocks_from_points(xyz: np.ndarray, instance: np.ndarray, center_score: np.ndarray,
                       part_radius: float, block_size: int, k: int,
                       skip_empty: bool = True, knn_near: int = 0,
                       knn_reach: int = 0, normals: bool = False) -> list[Block]:
    """Cut points into spatial blocks and compute each block's network inputs."""
    blocks = []
    for idx in spatial_blocks(xyz, block_size):
        inst = instance[idx].astype(np.int64)
        if skip_empty and not (inst > 0).any():
            continue
        pts = xyz[idx]
        features, knn = block_inputs(pts, part_radius, k, normals, knn_near, knn_reach)
        blocks.append(Block(features=features, knn=knn,
                            xyz=pts.astype(np.float32), instance=inst,
                            center_score=center_score[idx].astype(np.float32),
                            part_radius=part_radius, index=idx.astype(np.int64)))
    return blocks


def scene_blocks(scene: Scene, config: DataConfig, rng: np.random.Generator | None = None,
                 skip_empty: bool = True) -> SceneBlocks:
    """The scene's blocks; augmented when ``rng`` is given (see the module docstring)."""
    xyz, factor = scene.xyz, config.voxel_factor
    if rng is not None:
        xyz = augment_points(xyz, config, rng)
        factor *= rng.uniform(*config.voxel_jitter)
    keep, inverse = voxel_downsample(xyz, factor * scene.part_radius)
    if rng is not None and config.max_dropout > 0:
        keep = keep[rng.random(len(keep)) >= rng.uniform(0, config.max_dropout)]
        inverse = None
    if config.remove_floor:
        on_floor = dominant_plane(xyz[keep].astype(np.float64), plane_tolerance(scene.part_radius))
        if on_floor.any():
            keep, inverse = keep[~on_floor], None
    blocks = blocks_from_points(xyz[keep], scene.instance[keep], scene.center_score[keep],
                                scene.part_radius, config.block_size, config.k, skip_empty,
                                config.knn_near, config.knn_reach, config.normals)
    return SceneBlocks(rep=keep, inverse=inverse, blocks=blocks)


def augment_points(xyz: np.ndarray, config: DataConfig, rng: np.random.Generator) -> np.ndarray:
    """Rotate about the camera z axis (around the cloud's centroid) and scale by a small factor."""
    center = xyz.mean(axis=0)
    angle = rng.uniform(0, 2 * np.pi) if config.rotate else 0.0
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) * rng.uniform(*config.scale_jitter)
    return ((xyz - center) @ rot.T + center).astype(np.float32)


def collate(blocks: Sequence[Block]) -> dict[str, torch.Tensor]:
    """Stack blocks into a batch, padding smaller blocks to the largest by repeating their own
    points (a repeated point changes no max-pool); ``valid`` marks the real rows for the loss."""
    m = max(len(b.xyz) for b in blocks)

    def pad(arr: np.ndarray) -> np.ndarray:
        return arr[np.resize(np.arange(len(arr)), m)]

    batch = {
        "features": np.stack([pad(b.features) for b in blocks]),
        "knn": np.stack([pad(b.knn) for b in blocks]),
        "xyz": np.stack([pad(b.xyz) for b in blocks]),
        "instance": np.stack([pad(b.instance) for b in blocks]),
        "center_score": np.stack([pad(b.center_score) for b in blocks]),
        "valid": np.stack([np.arange(m) < len(b.xyz) for b in blocks]),
        "part_radius": np.array([b.part_radius for b in blocks], dtype=np.float32),
    }
    return {key: torch.from_numpy(value) for key, value in batch.items()}


class BlockDataset:
    """Blocks of a set of scenes, with per-epoch batches.

    Without augmentation blocks are computed once. With it, the cached scenes are kept
    pre-downsampled at half the smallest jittered voxel size (less memory, cheaper epochs) and
    cut again every epoch.
    """

    def __init__(self, paths: Sequence[str | Path], config: DataConfig = DataConfig(),
                 augment: bool = False, seed: int = 0):
        if not paths:
            raise ValueError("no scene NPZ files given; pass --data with a folder of scenes")
        self.config, self.augment, self.seed = config, augment, seed
        # each scene downsampled as it is read: full-resolution scenes (~6 MB each) are never all
        # held at once (1,764 scenes reached 17.5 GB that way before any was downsampled)
        factor = 0.5 * config.voxel_factor * config.voxel_jitter[0] if augment else 0.0
        self.scenes = [_predownsample(load_scene(p), factor) for p in paths]
        self._fixed = None if augment else [b for s in self.scenes
                                            for b in scene_blocks(s, config).blocks]

    def epoch_blocks(self, epoch: int) -> list[Block]:
        if self._fixed is not None:
            return self._fixed
        return [b for i, s in enumerate(self.scenes)
                for b in scene_blocks(s, self.config, np.random.default_rng([self.seed, epoch, i])).blocks]

    def batches(self, epoch: int, batch_size: int, shuffle: bool = True) -> list[list[Block]]:
        """Batches of blocks of similar size (less padding), in a seeded random order."""
        blocks = self.epoch_blocks(epoch)
        order = np.arange(len(blocks))
        rng = np.random.default_rng([self.seed, epoch, 1 << 20])
        if shuffle:
            rng.shuffle(order)
        chunk = 8 * batch_size
        for start in range(0, len(order), chunk):  # sort by size within chunks of 8 batches
            part = order[start:start + chunk]
            order[start:start + chunk] = part[np.argsort([-len(blocks[i].xyz) for i in part], kind="stable")]
        groups = [[blocks[i] for i in order[s:s + batch_size]] for s in range(0, len(order), batch_size)]
        if shuffle:
            groups = [groups[i] for i in rng.permutation(len(groups))]
        return groups

    def iter_batches(self, epoch: int, batch_size: int,
                     shuffle: bool = True) -> Iterator[dict[str, torch.Tensor]]:
        """Collated batches (features, knn, xyz, instance, center_score, valid, part_radius)."""
        for group in self.batches(epoch, batch_size, shuffle):
            yield collate(group)


def _predownsample(scene: Scene, factor: float) -> Scene:
    if factor <= 0:
        return scene
    keep, _ = voxel_downsample(scene.xyz, factor * scene.part_radius)
    keep = np.sort(keep)
    return replace(scene, xyz=scene.xyz[keep], instance=scene.instance[keep],
                   center_score=scene.center_score[keep])
