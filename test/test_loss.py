"""FPCC loss terms on tiny cases whose expected values are worked out by hand in the comments."""
import math

import pytest
import torch

from fpcc_ros.training.loss import (attention_scores, batch_loss, center_loss, embedding_loss,
                                    nearest_prototype_hits, prototype_loss,
                                    embedding_loss_fast,
                                    feature_distance, pair_hinge, same_instance, smooth_l1,
                                    total_loss, valid_distance_mask)

# Three points with 1-D embeddings 0, 0.8, 0.3 -> feature distances d01 = 0.8, d02 = 0.3, d12 = 0.5.
EMB = torch.tensor([[0.0], [0.8], [0.3]])


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """One torch thread: the machine is shared and spinning OpenMP threads stall under load."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_feature_distance_is_l2_not_squared():
    d = feature_distance(EMB)
    expected = torch.tensor([[0.0, 0.8, 0.3], [0.8, 0.0, 0.5], [0.3, 0.5, 0.0]])
    torch.testing.assert_close(d, expected, atol=2e-4, rtol=0)  # diagonal is sqrt(1e-8) = 1e-4
    # 2-D: (0,0)-(3,4) is 5 (a squared distance would be 25)
    d2 = feature_distance(torch.tensor([[0.0, 0.0], [3.0, 4.0]]))
    assert d2[0, 1].item() == pytest.approx(5.0, abs=1e-4)


def test_feature_distance_gradient_finite_for_identical_embeddings():
    emb = torch.ones(3, 4, requires_grad=True)
    feature_distance(emb).sum().backward()
    assert torch.isfinite(emb.grad).all()


def test_valid_distance_mask_strictly_below_two_d_max():
    xyz = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.22, 0.0, 0.0]])
    # d_max 0.1 -> pairs closer than 0.2 count: |01| = 0.05 yes, |12| = 0.17 yes, |02| = 0.22 no
    got = valid_distance_mask(xyz, 0.1)
    assert got.tolist() == [[True, True, False], [True, True, True], [False, True, True]]


def test_attention_scores_clip_at_one():
    s = torch.tensor([0.2, 0.5, 0.9])
    expected = torch.tensor([[0.4, 0.7, 1.0], [0.7, 1.0, 1.0], [1.0, 1.0, 1.0]])
    torch.testing.assert_close(attention_scores(s), expected)


def test_same_instance_background_matches_nothing():
    inst = torch.tensor([1, 1, 2, 0, 0])
    got = same_instance(inst)
    assert got.tolist() == [
        [True, True, False, False, False],
        [True, True, False, False, False],
        [False, False, True, False, False],
        [False, False, False, False, False],   # background vs background, even itself: different
        [False, False, False, False, False],
    ]


def test_pair_hinge_both_branches():
    d = torch.tensor([[0.3, 0.8], [0.8, 1.4]])
    same = torch.tensor([[True, True], [False, False]])
    # same: max(0, 0.3 - 0.5) = 0, max(0, 0.8 - 0.5) = 0.3; different: max(0, 1 - 0.8) = 0.2, max(0, 1 - 1.4) = 0
    torch.testing.assert_close(pair_hinge(d, same), torch.tensor([[0.0, 0.3], [0.2, 0.0]]))
    # other margins: same 0.8 - 0.7 = 0.1; different 2 - 0.8 = 1.2 and 2 - 1.4 = 0.6
    torch.testing.assert_close(pair_hinge(d, same, eps1=0.7, eps2=2.0), torch.tensor([[0.0, 0.1], [1.2, 0.6]]))


def test_embedding_loss_hand_case():
    xyz = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.22, 0.0, 0.0]])
    inst = torch.tensor([1, 1, 2])
    s = torch.tensor([0.2, 0.5, 0.9])
    # valid pairs (d_max 0.1): 3 diagonal + (0,1),(1,0) + (1,2),(2,1) = 7
    # (0,1) same,      d = 0.8: hinge 0.3, ASM min(1, 0.7) = 0.7 -> 0.21, twice
    # (1,2) different, d = 0.5: hinge 0.5, ASM min(1, 1.4) = 1   -> 0.5,  twice
    # (0,2) invalid (0.22 >= 0.2); diagonal: same instance, d ~ 0 -> hinge 0
    expected = (2 * 0.21 + 2 * 0.5) / 7
    got = embedding_loss(EMB, xyz, inst, s, d_max=0.1)
    assert got.item() == pytest.approx(expected, abs=1e-5)


def test_prototype_loss_hand_case():
    # part 1: core at 0 (score 0.9), rim at 0.4; part 2: core at 1 (0.8), rim at 0.7; background 5
    emb = torch.tensor([[0.0], [0.4], [1.0], [0.7], [5.0]])
    inst = torch.tensor([1, 1, 2, 2, 0])
    s = torch.tensor([0.9, 0.2, 0.8, 0.1, 0.0])
    # prototypes 0 and 1; logits -d^2 / 0.25 against (part 1, part 2); background left out
    def ce(own, other):
        return -own + math.log(math.exp(own) + math.exp(other))
    expected = (ce(0.0, -4.0) + ce(-0.64, -1.44) + ce(0.0, -4.0) + ce(-0.36, -1.96)) / 4
    assert prototype_loss(emb, inst, s).item() == pytest.approx(expected, abs=1e-5)
    # a rim point nearer the other part's prototype costs more than one nearer its own
    swapped = emb.clone()
    swapped[1] = 0.8
    assert prototype_loss(swapped, inst, s).item() > expected
    # one prototype only (part 2 has no point above the core score): nothing to tell apart
    assert prototype_loss(emb, inst, torch.tensor([0.9, 0.2, 0.5, 0.1, 0.0])).item() == 0.0


def test_nearest_prototype_hits_counts_points_nearest_their_own_part():
    # prototypes: part 1 at 0 (its points scoring > 0.7), part 2 at 1; part 3 has no core point
    emb = torch.tensor([[0.0], [0.4], [0.6], [1.0], [0.9], [0.2], [0.0], [5.0]])
    inst = torch.tensor([1, 1, 1, 2, 2, 2, 3, 0])
    s = torch.tensor([0.9, 0.2, 0.3, 0.8, 0.5, 0.1, 0.5, 0.0])
    # part 1: 0 hit, 0.4 hit, 0.6 miss (nearer 1); part 2: 1 hit, 0.9 hit, 0.2 miss;
    # part 3 (no prototype) and background are not counted
    assert nearest_prototype_hits(emb, inst, s) == (4, 6)
    assert nearest_prototype_hits(emb, inst, torch.zeros(8)) == (0, 0)


def test_embedding_loss_background():
    # point 2 is background with score 0; points 0 and 1 are one part.
    emb = torch.tensor([[0.0], [0.2], [0.6]])
    xyz = torch.zeros(3, 3)  # all pairs valid: 9 pairs
    inst = torch.tensor([1, 1, 0])
    s = torch.tensor([0.6, 0.3, 0.0])
    # (0,1) same, d 0.2 < 0.5 -> 0
    # (0,2) different, d 0.6: hinge 0.4, ASM 0.6 -> 0.24, twice
    # (1,2) different, d 0.4: hinge 0.6, ASM 0.3 -> 0.18, twice
    # (2,2) background with itself: "different", hinge ~1, but ASM = min(1, 0 + 0) = 0 -> 0
    # (0,0): ASM 1, same, hinge 0; (1,1): same -> 0
    expected = (2 * 0.24 + 2 * 0.18) / 9
    got = embedding_loss(emb, xyz, inst, s, d_max=0.1)
    assert got.item() == pytest.approx(expected, abs=1e-5)


def test_smooth_l1_both_branches():
    x = torch.tensor([0.5, -0.5, 0.0, 1.0, -2.0, 3.0])
    # |x| < 1: 0.5 x^2 -> 0.125, 0.125, 0; |x| >= 1: |x| - 0.5 -> 0.5, 1.5, 2.5
    torch.testing.assert_close(smooth_l1(x), torch.tensor([0.125, 0.125, 0.0, 0.5, 1.5, 2.5]))


def test_center_loss_is_mean():
    pred = torch.tensor([0.5, 0.9, 0.0, 0.2])
    target = torch.tensor([0.1, 0.9, 1.0, 0.0])
    # diffs 0.4, 0, 1, 0.2 -> 0.08, 0, 0.5, 0.02; mean 0.15
    assert center_loss(pred, target).item() == pytest.approx(0.15, abs=1e-6)


def test_total_loss_alpha_weighting():
    ef, cs = torch.tensor(0.2), torch.tensor(0.1)
    assert total_loss(ef, cs).item() == pytest.approx(0.5)           # default alpha = 3
    assert total_loss(ef, cs, alpha=1.0).item() == pytest.approx(0.3)


def _batch(emb, xyz, inst, s, pred_s, valid, radius):
    return emb, pred_s, {"xyz": xyz, "instance": inst, "center_score": s, "valid": valid,
                         "part_radius": torch.tensor(radius)}


def test_batch_loss_ignores_padding_and_averages_blocks():
    xyz = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.22, 0.0, 0.0]])
    inst = torch.tensor([1, 1, 2])
    s = torch.tensor([0.2, 0.5, 0.9])
    pred = torch.tensor([0.2, 0.5, 0.4])   # center errors 0, 0, 0.5 -> smooth-L1 0.125 on one point
    ef_hand = (2 * 0.21 + 2 * 0.5) / 7
    # block 0: the hand case plus a padded garbage row; block 1: the hand case with rows reversed
    pad = lambda t, v: torch.cat([t, v[None]])  # noqa: E731
    emb, pred_s, batch = _batch(
        torch.stack([pad(EMB, torch.tensor([9.0])), pad(EMB.flip(0), torch.tensor([-9.0]))]),
        torch.stack([pad(xyz, torch.zeros(3)), pad(xyz.flip(0), torch.zeros(3))]),
        torch.stack([pad(inst, torch.tensor(1)), pad(inst.flip(0), torch.tensor(2))]),
        torch.stack([pad(s, torch.tensor(1.0)), pad(s.flip(0), torch.tensor(1.0))]),
        torch.stack([pad(pred, torch.tensor(0.0)), pad(pred.flip(0), torch.tensor(0.0))]),
        torch.tensor([[True, True, True, False], [True, True, True, False]]), [0.1, 0.1])
    total, ef, cs = batch_loss(emb, pred_s, batch)
    assert ef.item() == pytest.approx(ef_hand, abs=1e-5)
    assert cs.item() == pytest.approx(2 * 0.125 / 6, abs=1e-6)
    assert total.item() == pytest.approx(ef_hand + 3 * 2 * 0.125 / 6, abs=1e-5)


def _definition_and_fast(emb, xyz, inst, s, d_max):
    """(values, gradients) of embedding_loss and embedding_loss_fast on the same inputs."""
    values, grads = [], []
    for fn in (embedding_loss, embedding_loss_fast):
        e = emb.clone().requires_grad_()
        value = fn(e, xyz, inst, s, d_max)
        value.backward()
        values.append(value.item())
        grads.append(e.grad)
    return values, grads


@pytest.mark.parametrize("seed", [0, 1])
def test_fast_embedding_loss_matches_definition_value_and_gradient(seed):
    torch.manual_seed(seed)
    n = 40
    emb = torch.randn(n, 6, dtype=torch.float64) * 0.4
    emb[1] = emb[0]                                       # an identical pair (D_F ~ 0)
    xyz = torch.rand(n, 3, dtype=torch.float64) * 0.2
    inst = torch.randint(0, 4, (n,))
    s = torch.rand(n, dtype=torch.float64) * (inst > 0)
    values, grads = _definition_and_fast(emb, xyz, inst, s, 0.05)
    assert values[0] > 0
    assert values[1] == pytest.approx(values[0], rel=1e-9)
    torch.testing.assert_close(grads[1], grads[0], atol=1e-9, rtol=1e-7)


@pytest.mark.parametrize("chunk", [7, 13, 40, 64])
def test_fast_embedding_loss_over_chunks_matches_definition(monkeypatch, chunk):
    """Row chunks meet only the columns from their own on (upper triangle): several chunks, a
    ragged last one and a single one all give the definition's value and gradient."""
    import fpcc_ros.training.loss as loss_module

    monkeypatch.setattr(loss_module, "_CHUNK", chunk)
    torch.manual_seed(3)
    n = 40
    emb = torch.randn(n, 5, dtype=torch.float64) * 0.5
    xyz = torch.rand(n, 3, dtype=torch.float64) * 0.2
    inst = torch.randint(0, 5, (n,))
    s = torch.rand(n, dtype=torch.float64) * (inst > 0)
    # 2 d_max = 0.08: some pairs valid, many not
    values, grads = _definition_and_fast(emb, xyz, inst, s, 0.04)
    assert 0 < values[0]
    assert values[1] == pytest.approx(values[0], rel=1e-9)
    torch.testing.assert_close(grads[1], grads[0], atol=1e-9, rtol=1e-7)
