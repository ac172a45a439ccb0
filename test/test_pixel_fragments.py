"""Fragments from pixel adjacency (fpcc_ros.fragments.pixel_fragments) on hand-made organized
clouds: a camera at the origin looking along +z, 2 mm between pixels."""
import numpy as np

from fpcc_ros.fragments import CREASE_CURVATURE, pixel_fragments

PITCH = 0.002
EPS = 0.009


def image(depth: np.ndarray) -> np.ndarray:
    """An organized (H*W, 3) cloud with the given per-pixel depth (NaN = no return)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    xyz = np.stack([u * PITCH, v * PITCH, depth], axis=-1).astype(np.float32)
    xyz[~np.isfinite(depth)] = np.nan
    return xyz.reshape(-1, 3)


def fragments(depth: np.ndarray, crease: float = 0.0) -> np.ndarray:
    xyz = image(depth)
    pixels = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    out = np.zeros(len(xyz), np.int64)
    out[pixels] = pixel_fragments(xyz, pixels, depth.shape, EPS, crease=crease)
    return out.reshape(depth.shape)


def test_one_flat_patch_is_one_fragment():
    labels = fragments(np.full((20, 30), 0.8))
    assert set(np.unique(labels)) == {1}


def test_depth_jump_splits_touching_surfaces_and_the_edge_stays_with_the_nearer():
    depth = np.full((20, 30), 0.80)
    depth[:, 15:] = 0.75            # the right half 50 mm nearer: two parts side by side
    labels = fragments(depth)
    left, right = labels[:, :15], labels[:, 15:]
    assert len(np.unique(left)) == 1 and len(np.unique(right)) == 1
    assert left[0, 0] != right[0, 0] and left[0, 0] > 0 and right[0, 0] > 0
    # the deeper side's edge column is cut from the core but still joins its own surface
    assert (labels[:, 14] == left[0, 0]).all()


def test_an_occluder_cuts_a_part_in_two():
    depth = np.full((20, 40), 0.80)   # a long part ...
    depth[:, 18:22] = 0.70            # ... with a bar lying across it, 100 mm nearer
    labels = fragments(depth)
    a, bar, b = labels[5, 2], labels[5, 19], labels[5, 35]
    assert len({a, bar, b}) == 3 and min(a, bar, b) > 0
    assert (labels[:, :18] == a).all() and (labels[:, 22:] == b).all()


def test_a_gap_of_missing_pixels_separates_and_a_lone_pixel_is_noise():
    depth = np.full((20, 30), 0.80)
    depth[:, 10:12] = np.nan          # no return between two patches
    depth[0:3, 20:23] = np.nan
    depth[1, 21] = 0.60               # one stray pixel, in a hole, far nearer: no neighbour
    labels = fragments(depth)
    assert labels[5, 0] != labels[5, 20] and labels[5, 0] > 0 and labels[5, 20] > 0
    assert labels[1, 21] == 0


def test_pixels_left_out_link_to_nothing():
    depth = np.full((10, 30), 0.80)
    xyz = image(depth)
    keep = np.arange(10 * 30).reshape(10, 30)
    pixels = np.concatenate([keep[:, :12].ravel(), keep[:, 14:].ravel()])  # columns 12-13 out
    out = pixel_fragments(xyz, pixels, (10, 30), EPS)
    left = out[pixels < 10 * 30][np.isin(pixels, keep[:, :12])]
    right = out[np.isin(pixels, keep[:, 14:])]
    assert len(np.unique(left)) == 1 and len(np.unique(right)) == 1
    assert left[0] != right[0]


def test_world_frame_depth_axis_picks_the_nearer_side():
    depth = np.full((20, 30), 0.80)
    depth[:, 15:] = 0.75
    xyz = image(depth)
    world = xyz * np.array([1.0, -1.0, -1.0], np.float32)   # a z-up frame, camera above: -z
    pixels = np.arange(len(xyz))
    labels = pixel_fragments(world, pixels, depth.shape, EPS, depth_axis=2,
                             depth_sign=-1.0).reshape(depth.shape)
    assert (labels[:, 14] == labels[0, 0]).all() and labels[0, 0] != labels[0, 20]


def two_shafts(noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Depth of two 15 mm shafts lying side by side along the image columns, touching: a
    valley between them that no xyz link distance separates (neighbour steps under 9 mm). The
    first and last 4 rows have no return (the floor removed), so the valley ends at a hole."""
    h, w = 24, 40
    x = (np.arange(w) + 0.5) * PITCH
    tops = [0.80 - np.sqrt(np.clip(0.015 ** 2 - (x - cx) ** 2, 0.0, None))
            for cx in (0.02, 0.05)]
    depth = np.tile(np.minimum(*tops), (h, 1))
    depth[:4] = depth[-4:] = np.nan
    return depth + np.random.default_rng(seed).normal(0.0, noise, depth.shape)


def test_touching_shafts_are_cut_at_their_concave_valley():
    depth = two_shafts()
    xyz = image(depth)
    pixels = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    assert len(np.unique(pixel_fragments(xyz, pixels, depth.shape, EPS))) == 1   # crease off
    labels = fragments(depth, CREASE_CURVATURE)
    left, right = labels[5:-5, 3:14], labels[5:-5, 21:32]   # each shaft, away from the valley
    assert len(np.unique(left)) == 1 and len(np.unique(right)) == 1
    assert left[0, 0] != right[0, 0] and min(left[0, 0], right[0, 0]) > 0


def test_convex_and_noisy_surfaces_are_not_cut():
    shaft = np.tile(0.80 - np.sqrt(np.clip(0.015 ** 2 - ((np.arange(15) + 0.5) * PITCH - 0.015)
                                           ** 2, 0.0, None)), (24, 1))
    assert set(np.unique(fragments(shaft, CREASE_CURVATURE))) == {1}   # one shaft's top: convex
    noisy = 0.80 + np.random.default_rng(3).normal(0.0, 0.0003, (40, 60))
    assert set(np.unique(fragments(noisy, CREASE_CURVATURE))) == {1}   # a plane, 0.3 mm noise


def test_creases_are_found_in_a_z_up_world_frame_too():
    depth = two_shafts(noise=0.0002, seed=1)
    world = image(depth) * np.array([1.0, -1.0, -1.0], np.float32)   # camera above: depth -z
    pixels = np.flatnonzero(np.isfinite(world).all(axis=1))
    labels = np.zeros(len(world), np.int64)
    labels[pixels] = pixel_fragments(world, pixels, depth.shape, EPS, depth_axis=2,
                                     depth_sign=-1.0, crease=CREASE_CURVATURE)
    labels = labels.reshape(depth.shape)
    assert labels[10, 5] != labels[10, 30] and min(labels[10, 5], labels[10, 30]) > 0


def test_a_fragment_that_fits_in_one_part_keeps_its_creases():
    depth = two_shafts()   # 80 x 32 mm, 15 mm deep: a diagonal of ~88 mm
    xyz = image(depth)
    pixels = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    whole = pixel_fragments(xyz, pixels, depth.shape, EPS, crease=CREASE_CURVATURE,
                            whole_diagonal=0.10)
    assert set(np.unique(whole)) == {1}          # fits a 100 mm part: its valley is the part's
    cut = pixel_fragments(xyz, pixels, depth.shape, EPS, crease=CREASE_CURVATURE,
                          whole_diagonal=0.05)
    cut = np.bincount(cut)[1:]
    assert len(cut) == 2 and cut.min() > 100     # larger than a 50 mm part: two shafts, ids 1, 2
