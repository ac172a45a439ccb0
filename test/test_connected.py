"""The connected clustering (clustering.connect_fragments, the pipeline's `connected` mode) and
the oracle that measures its ceiling, on hand-made clouds whose answers are worked out by hand."""
from pathlib import Path

import numpy as np
import pytest

from fpcc_ros.clustering import connect_fragments
from fpcc_ros.dbscan import dbscan
from fpcc_ros.evaluation import evaluate, f1_score
from fpcc_ros.model_card import ModelCard
from fpcc_ros.onnx_model import FpccModel
from fpcc_ros.oracle import ORACLE_HEADS, OraclePipeline, representative_truth
from fpcc_ros.pipeline import ConfigError, Pipeline, PipelineConfig

from test_evaluation import FLOOR, patch

TINY_MODEL = Path(__file__).resolve().parent / "data" / "tiny_fpcc.onnx"
STEP = 0.1   # grid spacing of the hand-made parts
EPS = 0.15   # DBSCAN eps: neighbours on the grid (0.1, diagonals 0.14) link, a 0.3 gap does not
D_MAX = 0.8  # a 1 x 1 square (diagonal 1.41) fits in a part (2 d_max = 1.6); two side by side do
#              not


def square(x: float, y: float = 0.0, n: int = 11) -> np.ndarray:
    """n x n grid points 0.1 apart, lower corner at (x, y), z = 0: 1.0 x 1.0 for n = 11."""
    g = np.arange(n) * STEP
    gx, gy = np.meshgrid(x + g, y + g, indexing="ij")
    return np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]


def fragments(xyz: np.ndarray) -> np.ndarray:
    return dbscan(xyz, EPS, 1)


def test_touching_parts_are_one_fragment_and_the_centers_split_them():
    # two squares with their edges 0.1 apart: one fragment by connectivity alone
    left, right = square(0.0), square(1.1)
    xyz = np.vstack([left, right])
    assert len(set(fragments(xyz))) == 1
    # the centers' point-wise labels: 1 on the left square, 2 on the right, except three
    # points on each side that the network got wrong (labelled 0 or the other center)
    labels = np.r_[np.ones(len(left), int), np.full(len(right), 2)]
    labels[[0, 1, 2]] = [0, 2, 0]
    labels[[130, 131]] = [1, 0]
    out = connect_fragments(labels, fragments(xyz), np.ones(len(xyz)), xyz, D_MAX, 10)
    # too big for one part (diagonal 2.33 > 1.6): split point by point between the claimants
    assert set(out[labels == 1]) == {1} and set(out[labels == 2]) == {2}
    assert (out[labels == 0] == 0).all()


def test_a_part_cut_by_an_occluder_is_joined_through_its_center():
    # one part (center 1) seen as two pieces 0.3 apart (an occluder lies across it), a second
    # part (center 2) elsewhere; the network labelled only part of each piece
    piece_a, piece_b = square(0.0, n=4), square(0.6, n=3)      # 0.3 and 0.2 wide, 0.3 apart:
    other = square(3.0, n=5)                                   # union 0.8 x 0.3, diagonal 0.85
    xyz = np.vstack([piece_a, piece_b, other])
    frag = fragments(xyz)
    assert len(set(frag)) == 3
    labels = np.r_[np.ones(len(piece_a), int), np.ones(len(piece_b), int), np.full(len(other), 2)]
    labels[:6] = 0                                   # unlabelled points inside piece a
    labels[len(piece_a):len(piece_a) + 4] = 0        # and inside piece b
    out = connect_fragments(labels, frag, np.ones(len(xyz)), xyz, D_MAX, 10)
    # each piece fits in a part and is claimed by center 1: both are its, whole
    assert (out[:len(piece_a) + len(piece_b)] == 1).all()
    assert (out[len(piece_a) + len(piece_b):] == 2).all()


def test_a_round_part_whose_box_diagonal_exceeds_two_d_max_is_still_one_part():
    # a disc of radius 0.75 (diameter 1.5 < 2 d_max = 1.6, box diagonal 2.1 > 1.6: the ring
    # screw's case), labelled by center 1 except a strip that center 2's votes took; center 2
    # has its own part far away. The disc fits in a part, so all of it is center 1's, and
    # center 2 keeps its own square
    g = np.arange(-0.75, 0.76, STEP)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    inside = gx ** 2 + gy ** 2 <= 0.75 ** 2 + 1e-9
    disc = np.c_[gx[inside], gy[inside], np.zeros(inside.sum())]
    other = square(5.0, n=6)
    xyz = np.vstack([disc, other])
    frag = fragments(xyz)
    assert len(set(frag)) == 2
    labels = np.r_[np.where(disc[:, 0] < -0.3, 2, 1), np.full(len(other), 2)]
    out = connect_fragments(labels, frag, np.ones(len(xyz)), xyz, D_MAX, 10)
    assert (out[:len(disc)] == 1).all()
    assert (out[len(disc):] == 2).all()


def test_a_fragment_without_a_center_is_kept_when_big_enough_else_dropped():
    claimed = square(0.0, n=6)                   # 36 points, center 1; diagonal 0.71
    big = square(2.0, n=6)                       # 36 points, no center
    small = square(4.0, n=5)                     # 25 points, no center; diagonal 0.57 >= 0.6 x 0.71
    wall = np.c_[np.arange(40) * STEP, np.full(40, 6.0), np.zeros(40)]  # 3.9 long: no part
    xyz = np.vstack([claimed, big, small, wall])
    labels = np.r_[np.ones(len(claimed), int), np.zeros(len(big) + len(small) + len(wall), int)]
    out = connect_fragments(labels, fragments(xyz), np.ones(len(xyz)), xyz, D_MAX, 30)
    a, b, c = len(claimed), len(claimed) + len(big), len(claimed) + len(big) + len(small)
    assert (out[:a] == 1).all()
    assert (out[a:b] == 2).all()                 # center labels 1..1, then the kept leftover
    assert (out[b:c] == 0).all()                 # 25 < 30 points
    assert (out[c:] == 0).all()                  # 40 points, but longer than 2 d_max
    # counted in input points: the small square's 25 rows standing for 2 points each are 50
    weights = np.ones(len(xyz))
    weights[b:c] = 2
    out = connect_fragments(labels, fragments(xyz), weights, xyz, D_MAX, 30)
    assert (out[b:c] == 3).all()


def test_a_fragment_without_a_center_much_shorter_than_the_parts_found_is_a_piece():
    # center 1 found a 1.0 x 1.0 part (diagonal 1.41); two unclaimed fragments with enough
    # points: 0.7 x 0.7 (diagonal 0.99, at least 0.6 x 1.41 = 0.85: a part of its own) and
    # 0.5 x 0.5 (diagonal 0.71 < 0.85: a piece cut off a part, dropped)
    found, whole, piece = square(0.0), square(2.0, n=8), square(4.0, n=6)
    xyz = np.vstack([found, whole, piece])
    labels = np.r_[np.ones(len(found), int), np.zeros(len(whole) + len(piece), int)]
    out = connect_fragments(labels, fragments(xyz), np.ones(len(xyz)), xyz, D_MAX, 20)
    a, b = len(found), len(found) + len(whole)
    assert (out[:a] == 1).all() and (out[a:b] == 2).all() and (out[b:] == 0).all()
    # with no center in the frame there is nothing to compare with: both are parts
    out = connect_fragments(np.zeros(len(xyz), int), fragments(xyz), np.ones(len(xyz)), xyz,
                            D_MAX, 20)
    assert (out[:a] == 1).all() and (out[a:b] == 2).all() and (out[b:] == 3).all()


def test_a_stray_label_does_not_join_two_parts():
    # center 1 owns square A; 3 of square B's 121 points carry its label too (under a fifth
    # of B and of center 1's labels): B is not its piece but a part without a center
    a, b = square(0.0), square(3.0)
    xyz = np.vstack([a, b])
    labels = np.r_[np.ones(len(a), int), np.zeros(len(b), int)]
    labels[len(a):len(a) + 3] = 1
    out = connect_fragments(labels, fragments(xyz), np.ones(len(xyz)), xyz, D_MAX, 10)
    assert (out[:len(a)] == 1).all() and (out[len(a):] == 2).all()


def test_a_center_whose_pieces_do_not_fit_in_one_part_keeps_its_largest():
    # center 1 claims two squares 3 apart (more than 2 d_max): it keeps the larger one, the
    # other becomes an instance of its own
    a, b = square(0.0, n=6), square(3.0, n=5)
    xyz = np.vstack([a, b])
    out = connect_fragments(np.ones(len(xyz), int), fragments(xyz), np.ones(len(xyz)), xyz,
                            D_MAX, 10)
    assert (out[:len(a)] == 1).all() and (out[len(a):] == 2).all()
    # pieces 0.5 apart (union 1.5 x 0.5, diagonal 1.58) join at the default 2 d_max (1.6), not
    # at a tighter 1.2 d_max (0.96)
    a, b = square(0.0, n=6), square(1.0, n=6)
    xyz = np.vstack([a, b])
    labels, frag, ones = np.ones(len(xyz), int), fragments(xyz), np.ones(len(xyz))
    assert (connect_fragments(labels, frag, ones, xyz, D_MAX, 10) == 1).all()
    tight = connect_fragments(labels, frag, ones, xyz, D_MAX, 10, join=1.2)
    assert len(set(tight[:len(a)])) == 1 and len(set(tight[len(a):])) == 1
    assert tight[0] != tight[-1] and min(tight) > 0


def test_no_fragments_or_no_centers():
    xyz = square(0.0, n=4)
    assert (connect_fragments(np.ones(16, int), np.zeros(16, int), np.ones(16), xyz, D_MAX, 1)
            == 0).all()
    assert (connect_fragments(np.zeros(16, int), np.ones(16, int), np.ones(16), xyz, D_MAX, 1)
            == 1).all()


def test_representative_truth_takes_the_majority_and_the_mean_score():
    inverse = np.array([0, 0, 0, 1, 1, 2])
    instance = np.array([4, 4, 0, 0, 7, 7])       # rep 1: a tie 0/7 goes to the smaller id
    score = np.array([0.9, 0.6, 0.0, 0.2, 0.4, 1.0])
    majority, mean = representative_truth(inverse, instance, score, 3)
    assert majority.tolist() == [4, 0, 7]
    assert np.allclose(mean, [0.5, 0.3, 1.0])


def _scene(parts: list[np.ndarray], d_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, instance (1..K, floor 0) and DESIGN's center score around each part's middle."""
    xyz = np.vstack(parts + [FLOOR]).astype(np.float32)
    instance = np.concatenate([np.full(len(p), i + 1) for i, p in enumerate(parts)]
                              + [np.zeros(len(FLOOR), int)])
    score = np.zeros(len(xyz))
    for i, p in enumerate(parts):
        rows = instance == i + 1
        mid = p.mean(axis=0)
        score[rows] = np.clip(1 - (np.linalg.norm(xyz[rows] - mid, axis=1) / d_max) ** 2, 0, 1)
    return xyz, instance, score


@pytest.mark.parametrize("clustering", ["paper", "connected"])
def test_the_oracle_segments_separate_parts_perfectly(tmp_path, clustering):
    # three 21 x 21 faces 25 mm apart above a floor; ground truth in place of the network.
    # Fragments: eps 10 mm on 5 mm cells link a face's 2.5 mm grid, not the 25 mm gaps
    parts = [patch(x, 0.05, z, step=0.0025, size=0.05) for x, z in
             ((0.0, 0.98), (0.075, 0.97), (0.15, 0.985))]
    xyz, instance, score = _scene(parts, 0.05)
    path = tmp_path / "scene.npz"
    np.savez(path, points=xyz, instance=instance.astype(np.int32),
             center_score=score.astype(np.float32), part_radius=np.float32(0.05))
    model = FpccModel(TINY_MODEL, threads=1)
    cfg = PipelineConfig.from_card(model.card, part_radius=0.05, clustering=clustering,
                                   voxel_size=0.0, fragment_eps=0.01, fragment_density=1,
                                   fragment_min_points=100, min_points=100)
    report = evaluate([path], Pipeline(model, cfg), baseline=False, oracle=ORACLE_HEADS)
    counts = report.fpcc_totals("visible")
    assert (counts.true_positives, counts.predictions, counts.ground_truths) == (3, 3, 3)
    assert f1_score(counts) == 1.0
    # the network itself is never run
    labels = OraclePipeline(Pipeline(model, cfg), instance, score).segment(xyz).labels
    assert len(set(labels[instance > 0])) == 3 and (labels[instance == 0] == 0).all()


def test_clustering_settings_are_validated():
    with pytest.raises(ConfigError, match="clustering"):
        PipelineConfig(part_radius=0.05, clustering="dbscan").validate()
    with pytest.raises(ConfigError, match="fragment_eps"):
        PipelineConfig(part_radius=0.05, fragment_eps=0.0).validate()
    with pytest.raises(ConfigError, match="fragment_density"):
        PipelineConfig(part_radius=0.05, fragment_density=0).validate()
    for bad in (-1.0, 5000.0, float("nan")):
        with pytest.raises(ConfigError, match="fragment_crease"):
            PipelineConfig(part_radius=0.05, fragment_crease=bad).validate()


def test_a_card_with_a_bad_crease_curvature_is_refused(tmp_path):
    import json
    import shutil

    from fpcc_ros.model_card import ModelCardError, card_path_for, load_card

    card = json.loads(card_path_for(TINY_MODEL).read_text())
    assert load_card(card_path_for(TINY_MODEL)).fragment_crease == 0.0   # older cards: off
    shutil.copy(TINY_MODEL, tmp_path / "m.onnx")
    path = card_path_for(tmp_path / "m.onnx")
    path.write_text(json.dumps({**card, "fragment_crease": 60}))
    assert load_card(path).fragment_crease == 60
    path.write_text(json.dumps({**card, "fragment_crease": -5}))
    with pytest.raises(ModelCardError, match="fragment_crease=-5 is invalid"):
        load_card(path)


def test_calibration_sweeps_fragment_settings_for_the_connected_clustering_only(tmp_path):
    from fpcc_ros.calibrate import calibrate

    parts = [patch(x, 0.05, 0.98, step=0.0025, size=0.05) for x in (0.0, 0.075)]
    xyz, instance, score = _scene(parts, 0.05)
    path = tmp_path / "scene.npz"
    np.savez(path, points=xyz, instance=instance.astype(np.int32),
             center_score=score.astype(np.float32), part_radius=np.float32(0.05))
    rows = calibrate(FpccModel(TINY_MODEL, threads=1), [path], [0.3], [1.0], merges=[0.0],
                     prototypes=[0.0], clusterings=["paper", "connected"],
                     fragment_eps_values=[0.005, 0.01], fragment_densities=[1],
                     fragment_min_points=[100])
    modes = sorted((r.clustering, r.fragment_eps) for r in rows)
    card = FpccModel(TINY_MODEL, threads=1).card
    assert modes == [("connected", 0.005), ("connected", 0.01), ("paper", card.fragment_eps)]
    assert all(r.counts.ground_truths == 2 for r in rows)
    rows = calibrate(FpccModel(TINY_MODEL, threads=1), [path], [0.3], [1.0], merges=[0.0],
                     prototypes=[0.0], clusterings=["paper", "connected"],
                     fragment_min_points=[100], fragment_creases=[0.0, 60.0])
    assert sorted((r.clustering, r.fragment_crease) for r in rows) == \
        [("connected", 0.0), ("connected", 60.0), ("paper", card.fragment_crease)]


def test_the_oracle_on_an_organized_cloud_uses_pixel_fragments(monkeypatch):
    # a 60 x 150 camera image, 2.5 mm pixels: a floor at 1 m and three 20 x 20 pixel faces
    # 30 mm above it, 20 pixels apart; passed with its image shape, fragments come from pixel
    # adjacency, and each face is one instance, the floor none
    h, w, pitch = 60, 150, 0.0025
    v, u = np.mgrid[0:h, 0:w]
    depth = np.full((h, w), 1.0)
    instance = np.zeros((h, w), int)
    for i, left in enumerate((20, 60, 100)):
        depth[20:40, left:left + 20] = 0.97
        instance[20:40, left:left + 20] = i + 1
    xyz = np.stack([u * pitch, v * pitch, depth], axis=-1).reshape(-1, 3).astype(np.float32)
    instance = instance.reshape(-1)
    score = np.zeros(len(xyz))
    for i in (1, 2, 3):
        rows = instance == i
        mid = xyz[rows].mean(axis=0)
        score[rows] = np.clip(1 - (np.linalg.norm(xyz[rows] - mid, axis=1) / 0.05) ** 2, 0, 1)
    import fpcc_ros.pipeline as pipeline_module
    calls = []
    real = pipeline_module.pixel_fragments
    monkeypatch.setattr(pipeline_module, "pixel_fragments",
                        lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    model = FpccModel(TINY_MODEL, threads=1)
    cfg = PipelineConfig.from_card(model.card, part_radius=0.05, clustering="connected",
                                   voxel_size=0.0, fragment_eps=0.004, fragment_min_points=100,
                                   min_points=100)
    result = OraclePipeline(Pipeline(model, cfg), instance, score).segment(xyz, (h, w))
    labels = result.labels
    assert calls == [(h, w)]
    assert len(set(labels[instance > 0])) == 3 and 0 not in set(labels[instance > 0])
    creases = []
    monkeypatch.setattr(pipeline_module, "pixel_fragments",
                        lambda *a, **k: creases.append(k["crease"]) or real(*a, **k))
    flat_faces = OraclePipeline(Pipeline(model, cfg.replace(fragment_crease=60.0)), instance,
                                score).segment(xyz, (h, w)).labels
    assert creases == [60.0] and (flat_faces == labels).all()   # flat faces: nothing to cut
    for i in (1, 2, 3):
        assert len(set(labels[instance == i])) == 1
    assert (labels[instance == 0] == 0).all()


class _FaceNetwork:
    """Stands in for FPCC-Net on the three faces of :func:`_three_faces`: it finds a center on
    the first face only (score 0.9 within 10 mm of its middle, 0 elsewhere), and embeds every
    point at the origin except the third face's outer points (farther than 10 mm from its
    middle), which it puts 3 away: beyond a feature gate of 1 from any center."""

    def __init__(self, middles: np.ndarray, origin: np.ndarray):
        self.card = ModelCard(name="faces", k=8, part_radius=0.05, block_size=4096)
        self.middles, self.origin = middles, origin

    def run(self, features: np.ndarray, knn: np.ndarray, global_stride: int = 1):
        xyz = features[0, :, :3].astype(np.float64) * 0.05 + self.origin
        near = np.linalg.norm(xyz[:, None] - self.middles[None], axis=2) <= 0.01
        score = np.where(near[:, 0], 0.9, 0.0).astype(np.float32)
        embedding = np.zeros((len(xyz), 8), np.float32)
        third = np.linalg.norm(xyz[:, :2] - self.middles[2, :2], axis=1) <= 0.03
        embedding[third & ~near[:, 2], 0] = 3.0
        return embedding[None], score[None]


def _three_faces() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Three 50 mm faces 100 mm apart (farther than d_max 0.05 from each other's middles), no
    floor; points, instance 1..3, DESIGN's center score, the faces' middles."""
    parts = [patch(x, 0.05, 0.98, step=0.0025, size=0.05) for x in (0.0, 0.15, 0.30)]
    xyz = np.vstack(parts).astype(np.float32)
    instance = np.concatenate([np.full(len(p), i + 1) for i, p in enumerate(parts)])
    middles = np.array([p.mean(axis=0) for p in parts])
    dist = np.linalg.norm(xyz - middles[instance - 1], axis=1)
    return xyz, instance, np.clip(1 - (dist / 0.05) ** 2, 0, 1), middles


@pytest.mark.parametrize("heads, labelled_faces, whole_faces", [
    (("center_score", "embedding"), {1, 2, 3}, {1, 2, 3}),   # ground truth for both
    (("embedding",), {1}, {1}),          # the network's centers: the first face only
    (("center_score",), {1, 2, 3}, {1, 2}),  # its embeddings: the third face's rim is cut off
])
def test_the_oracle_replaces_only_the_heads_it_is_given(heads, labelled_faces, whole_faces):
    xyz, instance, score, middles = _three_faces()
    network = _FaceNetwork(middles, xyz.min(axis=0).astype(np.float64))
    cfg = PipelineConfig(part_radius=0.05, voxel_size=0.0, remove_floor=False, min_points=1,
                         score_threshold=0.5, screening_factor=1.0, feature_gate=1.0,
                         block_size=4096)
    labels = OraclePipeline(Pipeline(network, cfg), instance, score, heads).segment(xyz).labels
    assert {f for f in (1, 2, 3) if (labels[instance == f] > 0).any()} == labelled_faces
    assert {f for f in (1, 2, 3) if (labels[instance == f] > 0).all()} == whole_faces
    for face in labelled_faces:   # never one instance across two faces
        assert len(set(labels[instance == face]) - {0}) == 1


def test_oracle_heads_are_checked():
    xyz, instance, score, middles = _three_faces()
    network = _FaceNetwork(middles, xyz.min(axis=0).astype(np.float64))
    with pytest.raises(ValueError, match="oracle heads"):
        OraclePipeline(Pipeline(network, PipelineConfig(part_radius=0.05)), instance, score,
                       ("centers",))
