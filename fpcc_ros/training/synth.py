"""Synthetic bin-picking scenes: physics drop of identical parts into a tote, depth camera render.

One scene = one fresh pybullet DIRECT client (so results depend on the seed only, never on the
worker that made them or on what it made before):

1. a randomised tote on a floor (tote.py), scaled down for small parts as real cells are;
2. K copies of the part dropped in waves from random collision-free poses above the tote, each
   wave settling for a bounded number of steps; parts that bounce out of the tote are removed;
3. a randomised depth camera above the tote (camera.py) renders depth and body ids; depth is
   back-projected to an organized cloud in the optical frame, then sensor effects are applied;
4. labels: instance 1..K per pixel (tote, floor, flying pixels and no-return pixels 0) and the
   paper's center score s = clip(1 - (||p - c|| / d_max)^2, 0, 1), computed from the noise-free
   point p and the instance's geometric center c, both in the camera frame.

The returned dict is the scene NPZ of DESIGN.md section 4 plus extras (see ``generate_scene``).
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fpcc_ros.training.camera import apply_sensor, backproject, random_camera, random_sensor, render
from fpcc_ros.training.mesh import CollisionAssets, PartModel, create_part_shapes, prepare_collision
from fpcc_ros.training.parts import make_part
from fpcc_ros.training.tote import ToteSpec, build_tote, random_tote

STEEL_DENSITY = 7850.0  # kg/m^3
TIMESTEP = 1.0 / 240.0


@dataclass(frozen=True)
class PhysicsConfig:
    """Drop and settle parameters (bounded so a 30-part scene stays within a few CPU seconds)."""
    parts_per_wave: int = 12
    wave_steps: int = 150           # per wave (0.6 s): parts fall and mostly come to rest
    settle_steps: int = 240         # after the last wave, stopped early once everything rests
    check_every: int = 30
    rest_linear: float = 0.02       # m/s
    rest_angular: float = 0.5       # rad/s
    part_friction: float = 0.5      # steel on steel / plastic tote, dry
    tote_friction: float = 0.5
    rolling_friction: float = 0.0005
    restitution: float = 0.1
    solver_iterations: int = 20


def scene_scale(part: PartModel) -> float:
    """Tote and camera-distance scale: 1 for parts with d_max >= 6 cm, down to 0.5 for small
    parts, so a small part still covers a few hundred pixels (as a real cell would be set up)."""
    return float(np.clip(part.d_max / 0.06, 0.5, 1.0))


def layer_copies(part: PartModel) -> float:
    """Copies in one layer of a pile: those that, lying flat (projected area ~0.7 of the two
    largest extents), would cover the nominal tote floor (scaled for small parts as in
    ``scene_scale``)."""
    e = np.sort(part.extents)[::-1]
    s = scene_scale(part)
    return (0.6 * s) * (0.4 * s) / max(0.7 * e[0] * e[1], 1e-6)


def default_parts_range(part: PartModel) -> tuple[int, int]:
    """(min, max) copies per scene: from a few parts on the tote floor to a pile about 2.5
    layers deep that hides the floor, at most 60 copies (long thin parts stop short of 2.5
    layers: a 0.18 m shaft at 1.7)."""
    layer = layer_copies(part)
    lo = int(np.clip(round(0.15 * layer), 3, 10))
    hi = int(np.clip(round(2.5 * layer), lo + 5, 60))
    return lo, hi


def dense_parts_range(part: PartModel) -> tuple[int, int]:
    """(min, max) copies for a full bin, 1 to 2.5 layers deep, at most 100 copies.

    The default range's cap of 60 keeps 9 of the 14 built-in parts below 2.5 layers, while the
    IPA piles the default model is measured on are 2-2.8 layers deep (64-90 gear shafts)."""
    layer = layer_copies(part)
    hi = int(min(round(2.5 * layer), 100))
    return max(default_parts_range(part)[0], min(int(round(layer)), hi - 5)), hi


def resolve_part(part: PartModel | str, part_seed: int = 0) -> PartModel:
    """A PartModel, or a built-in part name built with ``part_seed``."""
    return part if isinstance(part, PartModel) else make_part(part, part_seed)


def _spawn_positions(rng: np.random.Generator, n: int, tote: ToteSpec, r: float, z_base: float) -> np.ndarray:
    """n centers above the tote whose bounding spheres (radius r) do not overlap."""
    mx = max(tote.inner[0] / 2 - r, 0.0)
    my = max(tote.inner[1] / 2 - r, 0.0)
    placed: list[np.ndarray] = []
    z_lo = z_base + r
    for _ in range(n):
        for _attempt in range(40):
            c = np.array([rng.uniform(-mx, mx), rng.uniform(-my, my), rng.uniform(z_lo, z_lo + 2 * r)])
            if all(np.linalg.norm(c - q) >= 2.05 * r for q in placed):
                break
        else:
            z_lo += 2.05 * r  # no room in this layer: open a new one above
            c = np.array([rng.uniform(-mx, mx), rng.uniform(-my, my), z_lo + 2.05 * r])
        placed.append(c)
    return np.array(placed)


def _random_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)  # uniform on SO(3); pybullet order xyzw


def _at_rest(p, client: int, bodies: list[int], cfg: PhysicsConfig) -> bool:
    for b in bodies:
        lin, ang = p.getBaseVelocity(b, physicsClientId=client)
        if np.linalg.norm(lin) > cfg.rest_linear or np.linalg.norm(ang) > cfg.rest_angular:
            return False
    return True


def _simulate(p, client: int, bodies: list[int], steps: int, cfg: PhysicsConfig) -> None:
    for k in range(steps):
        p.stepSimulation(physicsClientId=client)
        checkpoint = (k + 1) % cfg.check_every == 0 and k + 1 >= 2 * cfg.check_every
        if checkpoint and _at_rest(p, client, bodies, cfg):
            return


def drop_parts(client: int, part: PartModel, assets: CollisionAssets, tote: ToteSpec, k: int,
               rng: np.random.Generator, cfg: PhysicsConfig) -> list[int]:
    """Drop k copies into the tote in waves; returns the ids of the bodies that stay in it."""
    import pybullet as p  # training-only dependency
    col, vis = create_part_shapes(client, assets)
    mass = STEEL_DENSITY * part.volume if part.volume > 0 else 0.2
    bodies: list[int] = []
    remaining = k
    while remaining > 0:
        n = min(cfg.parts_per_wave, remaining)
        remaining -= n
        top = max([p.getBasePositionAndOrientation(b, physicsClientId=client)[0][2] for b in bodies] or [0.0])
        z_base = max(tote.rim_z, top + part.d_max) + 0.02
        pos = _spawn_positions(rng, n, tote, part.d_max, z_base)
        quat = _random_quaternions(rng, n)
        wave = []
        for c, q in zip(pos, quat):
            b = p.createMultiBody(mass, col, vis, basePosition=c.tolist(), baseOrientation=q.tolist(),
                                  physicsClientId=client)
            p.changeDynamics(b, -1, lateralFriction=cfg.part_friction, rollingFriction=cfg.rolling_friction,
                             spinningFriction=cfg.rolling_friction, restitution=cfg.restitution,
                             physicsClientId=client)
            wave.append(b)
        bodies += wave
        _simulate(p, client, bodies, cfg.wave_steps, cfg)
    _simulate(p, client, bodies, cfg.settle_steps, cfg)
    keep = []
    for b in bodies:
        (x, y, z), _ = p.getBasePositionAndOrientation(b, physicsClientId=client)
        if tote.contains_xy(np.array([[x, y]]))[0] and z > tote.floor_z - 0.01:
            keep.append(b)
        else:
            p.removeBody(b, physicsClientId=client)
    return keep


def _pose_matrix(pos, quat_xyzw) -> np.ndarray:
    x, y, z, w = quat_xyzw
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = pos
    return T


def center_scores(points: np.ndarray, instance: np.ndarray, centers: np.ndarray, d_max: float) -> np.ndarray:
    """Paper eq. 3 (beta = 2): clip(1 - (||p - c_instance|| / d_max)^2, 0, 1); 0 where instance 0."""
    idx = np.clip(instance - 1, 0, max(len(centers) - 1, 0))
    c = centers[idx] if len(centers) else np.zeros(points.shape, points.dtype)
    d2 = ((points - c) ** 2).sum(axis=-1) / d_max ** 2
    s = np.clip(1.0 - d2, 0.0, 1.0)
    return np.where(instance > 0, s, 0.0)


def generate_scene(part: PartModel | str, num_parts: int | None = None, seed: int = 0, *,
                   parts_range: tuple[int, int] | None = None, width: int = 640, height: int = 480,
                   noise: bool = True, part_seed: int = 0, physics: PhysicsConfig | None = None,
                   assets: CollisionAssets | None = None, cache_dir: str | None = None) -> dict:
    """One synthetic scene as the scene NPZ dict.

    Keys: ``points`` (H, W, 3) float32 optical frame, NaN = no return; ``instance`` (H, W) int32
    (0 = tote/floor/flying/no return); ``center_score`` (H, W) float32; ``part_radius`` (d_max,
    m); ``camera_K`` (3, 3); ``camera_pose`` (4, 4) optical frame -> world (z up, floor z = 0,
    tote centered at the origin); ``tote_inner`` (3,) inner length, width, height (m);
    ``part_name``; ``seed``; ``num_parts`` K (copies left in the tote); ``visible_points``
    (K + 1,) int32 labelled points per instance (index 0 unused); ``centers`` (K, 3) float32
    geometric centers in the camera frame; ``part_poses`` (K, 4, 4) float32 mesh frame ->
    camera frame. ``num_parts`` None draws K from ``parts_range`` (default:
    ``default_parts_range``). ``noise=False`` gives the ideal depth (no noise, dropouts or flying
    pixels).
    """
    import pybullet as p  # training-only dependency
    part = resolve_part(part, part_seed)
    cfg = physics or PhysicsConfig()
    assets = assets or prepare_collision(part, cache_dir)
    rng = np.random.default_rng(seed)
    scale = scene_scale(part)
    if num_parts is None:
        lo, hi = parts_range or default_parts_range(part)
        num_parts = int(rng.integers(lo, hi + 1))
    if num_parts < 1:
        raise ValueError(f"num_parts must be >= 1, got {num_parts}")
    tote = random_tote(rng, scale)
    client = p.connect(p.DIRECT)
    try:
        p.setPhysicsEngineParameter(fixedTimeStep=TIMESTEP, numSolverIterations=cfg.solver_iterations,
                                    deterministicOverlappingPairs=1, physicsClientId=client)
        p.setGravity(0, 0, -9.81, physicsClientId=client)
        build_tote(client, tote, cfg.tote_friction)
        bodies = drop_parts(client, part, assets, tote, num_parts, rng, cfg)
        poses_world = np.array([_pose_matrix(*p.getBasePositionAndOrientation(b, physicsClientId=client))
                                for b in bodies]).reshape(-1, 4, 4)
        cam = random_camera(rng, np.array([0.0, 0.0, tote.floor_z]), width=width, height=height,
                            height_range=(0.9 * scale, 1.6 * scale))
        z, seg = render(client, cam)
    finally:
        p.disconnect(physicsClientId=client)
    k = len(bodies)
    lut = np.zeros(max(bodies + [int(seg.max()), 0]) + 2, np.int32)  # body id -> instance
    lut[np.array(bodies, int) + 1] = np.arange(1, k + 1)
    inst_true = lut[seg + 1]
    # body frame = centered mesh frame: its origin is the geometric center
    T_cw = cam.T_cam_world
    body_cam = T_cw[None] @ poses_world
    centers = body_cam[:, :3, 3]
    to_body = np.eye(4)
    to_body[:3, 3] = -part.center
    part_poses = body_cam @ to_body[None]
    sensor = random_sensor(rng, noise)
    z_meas, flying = apply_sensor(z, cam.K, sensor, rng)
    pts_true = backproject(z, cam.K)
    score = center_scores(pts_true, inst_true, centers, part.d_max)
    points = backproject(z_meas, cam.K).astype(np.float32)
    valid = np.isfinite(z_meas)
    instance = np.where(valid & ~flying, inst_true, 0).astype(np.int32)
    score = np.where(instance > 0, score, 0.0).astype(np.float32)
    visible = np.bincount(instance.reshape(-1), minlength=k + 1).astype(np.int32)
    visible[0] = 0
    return {
        "points": points,
        "instance": instance,
        "center_score": score,
        "part_radius": np.float64(part.d_max),
        "camera_K": cam.K.astype(np.float64),
        "camera_pose": cam.T_world_cam.astype(np.float64),
        "tote_inner": np.array(tote.inner, np.float64),
        "part_name": np.str_(part.name),
        "seed": np.int64(seed),
        "num_parts": np.int32(k),
        "visible_points": visible,
        "centers": centers.astype(np.float32).reshape(k, 3),
        "part_poses": part_poses.astype(np.float32).reshape(k, 4, 4),
    }


# --------------------------------------------------------------------------------------------
# datasets
# --------------------------------------------------------------------------------------------

def _scene_job(job: tuple) -> tuple[int, int, int]:
    """Worker: make scene ``index`` and write it; returns (index, K, instances >= 300 points)."""
    index, path, part, kwargs, compress = job
    scene = generate_scene(part, **kwargs)
    tmp = Path(str(path) + f".{os.getpid()}.tmp.npz")
    (np.savez_compressed if compress else np.savez)(tmp, **scene)
    os.replace(tmp, path)
    return index, int(scene["num_parts"]), int((scene["visible_points"][1:] >= 300).sum())


def generate_dataset(out_dir: str | os.PathLike, part: PartModel | str, num_scenes: int, seed: int = 0, *,
                     workers: int = 1, parts_range: tuple[int, int] | None = None, width: int = 640,
                     height: int = 480, noise: bool = True, part_seed: int = 0, compress: bool = True,
                     progress: bool = True, cache_dir: str | None = None) -> list[Path]:
    """Write ``scene_00000.npz`` ... to ``out_dir`` (scene i uses seed + i) and ``synth.json``.

    Scenes are independent, so ``workers`` processes (each with its own pybullet client) give
    identical files to a single process. The part's collision shapes are prepared once here.
    """
    from tqdm import tqdm
    part = resolve_part(part, part_seed)
    if num_scenes < 1:
        raise ValueError(f"num_scenes must be >= 1, got {num_scenes}")
    if parts_range is not None and not (1 <= parts_range[0] <= parts_range[1]):
        raise ValueError(f"parts range must satisfy 1 <= MIN <= MAX, got {parts_range}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    assets = prepare_collision(part, cache_dir)
    rng_range = parts_range or default_parts_range(part)
    kwargs = dict(parts_range=rng_range, width=width, height=height, noise=noise, assets=assets)
    jobs = [(i, out / f"scene_{i:05d}.npz", part, dict(kwargs, seed=seed + i), compress)
            for i in range(num_scenes)]
    meta = {"part_name": part.name, "part_source": part.source, "part_radius": part.d_max,
            "part_center": part.center.tolist(), "part_seed": part_seed, "collision": assets.kind,
            "num_scenes": num_scenes, "seed": seed, "parts_range": list(rng_range),
            "width": width, "height": height, "noise": noise}
    (out / "synth.json").write_text(json.dumps(meta, indent=2) + "\n")
    bar = tqdm(total=num_scenes, desc=f"synth {part.name}", unit="scene", disable=not progress)
    stats = []
    try:
        if workers <= 1:
            for job in jobs:
                stats.append(_scene_job(job))
                bar.update()
        else:
            with mp.get_context("spawn").Pool(workers) as pool:
                for res in pool.imap_unordered(_scene_job, jobs):
                    stats.append(res)
                    bar.update()
                    bar.set_postfix(parts=res[1], visible=res[2])
    finally:
        bar.close()
    return [job[1] for job in jobs]
