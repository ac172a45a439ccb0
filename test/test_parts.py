"""Built-in procedural parts: closed, sized as stated, right topology, reproducible."""
from __future__ import annotations

import numpy as np
import pytest

from fpcc_ros.training.parts import BUILTIN_PARTS, make_part

SEEDS = range(4)


def test_library_has_at_least_eight_parts():
    assert len(BUILTIN_PARTS) >= 8
    for name in ("stepped_shaft", "gear_shaft", "ring", "washer", "eye_bolt", "l_bracket", "hex_nut",
                 "flange", "pipe_elbow", "pipe_tee", "box_housing"):
        assert name in BUILTIN_PARTS


@pytest.mark.parametrize("name", sorted(BUILTIN_PARTS))
def test_part_is_closed_and_within_stated_ranges(name):
    spec = BUILTIN_PARTS[name]
    for seed in SEEDS:
        mesh = spec.factory(np.random.default_rng(seed))
        assert len(mesh.faces) > 0
        assert mesh.is_watertight and mesh.is_winding_consistent, f"{name} seed {seed} not closed"
        assert mesh.volume > 0
        part = make_part(name, seed)
        ext = part.extents.max()
        assert 0.03 <= ext <= 0.25, f"{name} seed {seed}: extent {ext:.3f} m outside 3-25 cm"
        assert spec.extent[0] <= ext <= spec.extent[1], f"{name} seed {seed}: extent {ext:.3f}"
        assert spec.d_max[0] <= part.d_max <= spec.d_max[1], f"{name} seed {seed}: d_max {part.d_max:.3f}"
        # d_max is at least half the largest extent and at most the bounding-box diagonal
        assert ext / 2 - 1e-9 <= part.d_max <= np.linalg.norm(part.extents) + 1e-9


# Euler characteristic V - E + F summed over the closed sub-solids: 2 per sphere-like piece,
# 2 - 2g for a piece with g through-holes (a ring, tube or washer has g = 1).
EULER = {
    "stepped_shaft": {2},              # one solid of revolution
    "gear_shaft": {6},                 # shaft, gear, shaft
    "ring": {0}, "washer": {0}, "pulley": {0}, "pipe_elbow": {0},
    "pipe_tee": {0},                   # two tubes
    "eye_bolt": {4},                   # torus eye + collar + shank
    "hex_nut": {0},
    "hex_bolt": {4},                   # head + shank
    "flange": {-8, -12, -16},          # disc with bore and 4/6/8 bolt holes (genus 5/7/9) + hub ring
}


@pytest.mark.parametrize("name", sorted(EULER))
def test_topology(name):
    for seed in SEEDS:
        mesh = BUILTIN_PARTS[name].factory(np.random.default_rng(seed))
        assert mesh.euler_number in EULER[name], f"{name} seed {seed}: euler {mesh.euler_number}"


def test_brackets_have_holes_in_every_plate():
    for name, plates in (("l_bracket", 2), ("u_bracket", 3)):
        for seed in SEEDS:
            mesh = BUILTIN_PARTS[name].factory(np.random.default_rng(seed))
            bodies = mesh.split(only_watertight=True)
            assert len(bodies) == plates
            # every plate has one or two holes: Euler 0 or -2
            assert all(b.euler_number in (0, -2) for b in bodies), [b.euler_number for b in bodies]


def test_washer_volume_is_annulus():
    for seed in SEEDS:
        mesh = BUILTIN_PARTS["washer"].factory(np.random.default_rng(seed))
        r = np.hypot(mesh.vertices[:, 0], mesh.vertices[:, 1])
        t = np.ptp(mesh.vertices[:, 2])
        n = 48  # facets of the revolved profile: polygon area (n/2) r^2 sin(2 pi / n)
        expected = 0.5 * n * np.sin(2 * np.pi / n) * (r.max() ** 2 - r.min() ** 2) * t
        assert mesh.volume == pytest.approx(expected, rel=1e-6)
        assert 0.002 <= t <= 0.006


def test_hex_nut_volume_is_prism_minus_bore():
    for seed in SEEDS:
        mesh = BUILTIN_PARTS["hex_nut"].factory(np.random.default_rng(seed))
        r = np.hypot(mesh.vertices[:, 0], mesh.vertices[:, 1])
        h = np.ptp(mesh.vertices[:, 2])
        hexagon = 1.5 * np.sqrt(3) * r.max() ** 2
        n_bore = int(np.sum(np.isclose(r, r.min()) & np.isclose(mesh.vertices[:, 2], 0)))
        bore = 0.5 * n_bore * np.sin(2 * np.pi / n_bore) * r.min() ** 2
        # the hexagon's edges bulge outward by 1e-4 of their length (see parts._densify_convex)
        assert mesh.volume == pytest.approx((hexagon - bore) * h, rel=1e-3)


def test_same_seed_same_part_and_different_seed_differs():
    for name in BUILTIN_PARTS:
        a, b = make_part(name, 3), make_part(name, 3)
        np.testing.assert_array_equal(a.vertices, b.vertices)
        c = make_part(name, 4)
        assert a.vertices.shape != c.vertices.shape or not np.allclose(a.vertices, c.vertices)


def test_unknown_part_lists_names():
    with pytest.raises(KeyError, match="gear_shaft"):
        make_part("no_such_part")
