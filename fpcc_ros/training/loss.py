"""FPCC loss (paper Sec. Training phase): L = L_EF + alpha * L_CS.

Each matrix of the paper is one small function on a single block (N points), so each can be
checked by hand. Choices where the paper and the reference code differ:

* D_F is the L2 feature distance (paper), not the squared distance (reference code). The square
  root gets a small epsilon so its gradient stays finite for identical embeddings.
* Same-instance pairs have weight 1 in the hinge (paper), not 2 (reference code).
* Background points (instance 0) are "different" from every point, themselves included, so they
  are pushed away from the part centers; background-background pairs have ASM weight 0 anyway
  (their center scores are 0), so they never contribute.
* Normalisation: the paper writes a plain sum; the reference divides by all B*N*N pairs. We
  divide by the number of valid pairs (sum of the VDM), i.e. L_EF is the mean weighted hinge over
  pairs closer than 2 d_max. That keeps L_EF's scale independent of how large a block is in
  metres (block_size, voxel size, part size change the fraction of valid pairs by several times),
  so alpha means the same balance whatever the block size we train with. At initialisation on
  synthetic piles L_EF ~0.2-0.5 and 3 L_CS ~0.3, but L_EF falls much faster: late in training
  3 L_CS was ~85 % of the loss, so ``fpcc train`` uses alpha = 1 (train.TRAIN_ALPHA, where the
  measurements are). ALPHA below stays the paper's 3, the default of :func:`total_loss`.

One term the paper does not have, off unless asked for (``fpcc train --prototype W``):
:func:`prototype_loss`, a cross-entropy that asks each part point to lie nearer its own part's
center prototype than any other part's. Measured on validation blocks of a 30-minute gear-shaft
fine-tune: 66 % of same-part pairs sat beyond eps1 while 91 % of different-part pairs sat beyond
eps2, and 11 % of part points lay nearer another part's prototype than their own. The hinge pays
no heed to which of two near centers a point is closer to; this term does. Weighting
same-instance pairs 2 instead (the reference code's choice) moved that 11 % nowhere. With W 0.05
the gear shaft's share fell to 7.5 % and its test F1 rose 0.02-0.04 (two seeds); the ring screw
(9.5 % without it) did not gain, so the term stays off by default (README, `--prototype`).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

EPS1 = 0.5
EPS2 = 1.0
ALPHA = 3.0
_SQRT_EPS = 1e-8


def feature_distance(embedding: torch.Tensor) -> torch.Tensor:
    """D_F (N, N): L2 distances between the rows of ``embedding`` (N, C), gradient-safe at 0."""
    sq_norm = (embedding * embedding).sum(dim=-1)
    sq = sq_norm[:, None] + sq_norm[None, :] - 2.0 * embedding @ embedding.T
    return torch.sqrt(sq.clamp_min(0.0) + _SQRT_EPS)


def valid_distance_mask(xyz: torch.Tensor, d_max: float) -> torch.Tensor:
    """D_V (N, N) bool: pairs closer than 2 d_max in 3D (metres); farther pairs cannot share a part."""
    return torch.cdist(xyz, xyz) < 2.0 * d_max


def attention_scores(center_score: torch.Tensor) -> torch.Tensor:
    """S_A (N, N) = min(1, s_i + s_j) from ground-truth center scores: pairs near a center count most."""
    return (center_score[:, None] + center_score[None, :]).clamp_max(1.0)


def same_instance(instance: torch.Tensor) -> torch.Tensor:
    """(N, N) bool: both points on the same part. Background (0) matches nothing, not even itself."""
    return (instance[:, None] == instance[None, :]) & (instance[:, None] > 0)


def pair_hinge(distance: torch.Tensor, same: torch.Tensor, eps1: float = EPS1,
               eps2: float = EPS2) -> torch.Tensor:
    """kappa (N, N): max(0, D - eps1) for same-instance pairs, max(0, eps2 - D) otherwise."""
    return torch.where(same, F.relu(distance - eps1), F.relu(eps2 - distance))


def embedding_loss(embedding: torch.Tensor, xyz: torch.Tensor, instance: torch.Tensor,
                   center_score: torch.Tensor, d_max: float, eps1: float = EPS1,
                   eps2: float = EPS2) -> torch.Tensor:
    """L_EF of one block: sum(D_V * S_A * kappa) / sum(D_V).

    ``embedding`` (N, C) predicted; ``xyz`` (N, 3) metres, ``instance`` (N,) and ``center_score``
    (N,) ground truth; ``d_max`` the part radius in metres.
    """
    valid = valid_distance_mask(xyz, d_max)
    weight = torch.where(valid, attention_scores(center_score), 0.0)
    kappa = pair_hinge(feature_distance(embedding), same_instance(instance), eps1, eps2)
    return (weight * kappa).sum() / valid.sum().clamp_min(1)


CORE_SCORE = 0.7   # a part's prototype: its points with a ground-truth center score above this


def core_prototypes(embedding: torch.Tensor, instance: torch.Tensor, center_score: torch.Tensor,
                    core: float = CORE_SCORE) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(prototypes (P, C), rows (N,) bool, own (R,)): the mean embedding of each part's points
    near its center (ground-truth score above ``core``), which is what the runtime compares
    points with; the part points whose part has one; and the row of its own prototype for each."""
    has_core = (instance > 0) & (center_score > core)
    ids, slot = torch.unique(instance[has_core], return_inverse=True)
    sums = embedding.new_zeros(len(ids), embedding.shape[1]).index_add_(0, slot, embedding[has_core])
    counts = torch.bincount(slot, minlength=len(ids)).to(embedding.dtype)
    own = torch.searchsorted(ids, instance).clamp_max(max(len(ids) - 1, 0))
    rows = (instance > 0) & (ids[own] == instance) if len(ids) else instance < 0
    return sums / counts[:, None], rows, own[rows]


def prototype_loss(embedding: torch.Tensor, instance: torch.Tensor, center_score: torch.Tensor,
                   temperature: float = 0.25) -> torch.Tensor:
    """Cross-entropy of each part point against the block's part prototypes (core_prototypes):
    logits -D^2 / ``temperature``, its own part the target.

    The hinge only asks pairs to sit inside / beyond fixed margins; this asks every point to be
    nearest its own part, the per-point decision clustering makes. 0 when the block holds fewer
    than two prototypes.
    """
    prototypes, rows, own = core_prototypes(embedding, instance, center_score)
    if len(prototypes) < 2:
        return embedding.sum() * 0.0
    sq = torch.cdist(embedding[rows], prototypes).square()
    return F.cross_entropy(-sq / temperature, own)


def nearest_prototype_hits(embedding: torch.Tensor, instance: torch.Tensor,
                           center_score: torch.Tensor) -> tuple[int, int]:
    """(hits, points): how many part points lie nearer their own part's prototype than any other
    part's in the block. Ground-truth parts, no clustering settings: a trained network's
    embedding quality by itself (with ground-truth embeddings every point is a hit)."""
    prototypes, rows, own = core_prototypes(embedding, instance, center_score)
    if len(prototypes) == 0:
        return 0, 0
    nearest = torch.cdist(embedding[rows], prototypes).argmin(dim=1)
    return int((nearest == own).sum()), len(own)


def smooth_l1(x: torch.Tensor) -> torch.Tensor:
    """0.5 x^2 where |x| < 1, |x| - 0.5 elsewhere (elementwise)."""
    ax = x.abs()
    return torch.where(ax < 1.0, 0.5 * x * x, ax - 0.5)


def center_loss(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_CS = mean smooth-L1(s - s_hat) over the points given."""
    return smooth_l1(target - predicted).mean()


def distill_loss(embedding: torch.Tensor, center_score: torch.Tensor, teacher_embedding: torch.Tensor,
                 teacher_score: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean over the real points of |e - e_teacher|^2 + (s - s_teacher)^2.

    For training a narrower net from a trained one (``fpcc train --teacher``): every point gets a
    128-d target, where L_EF's hinge is zero for most pairs once they sit inside eps1 / beyond
    eps2. (A net cut to EdgeConv 32 / global 512: 48 min from the labels gave validation F1
    0.498, 81 more with the shipped net as teacher 0.525-0.537, the teacher 0.578.)
    """
    de = (embedding - teacher_embedding)[valid]
    ds = (center_score - teacher_score)[valid]
    return (de * de).sum(dim=-1).mean() + (ds * ds).mean()


def total_loss(loss_ef: torch.Tensor, loss_cs: torch.Tensor, alpha: float = ALPHA) -> torch.Tensor:
    """L = L_EF + alpha L_CS."""
    return loss_ef + alpha * loss_cs


_CHUNK = 256


class _EmbeddingLoss(torch.autograd.Function):
    """``embedding_loss`` computed in row chunks with its gradient formed in the forward pass.

    Autograd of the N x N definition makes ~40 passes over 16.7M-element matrices per block at
    N = 4096 (memory bound, ~1 s). Here every N x N quantity exists only for _CHUNK rows at a
    time (a few MB, cache resident) and the gradient is closed-form: with W the (symmetric)
    pair weights and G = dL/d(D_F^2) = W * kappa'(D_F) / (2 D_F) (symmetric),
    dL/dE = 4 (rowsum(G) E - G E).

    Every pair term is symmetric, so each chunk of rows meets only itself and the columns after
    it (the upper triangle, about half the pairs): a pair off the chunk's own square counts
    twice in the sum and sends its gradient to both of its rows. About half the elementwise work
    of the full square: a block of 1,350 points took 0.70x the time (2 threads, 50 -> 37 ms).
    """

    @staticmethod
    def forward(ctx, embedding, xyz, instance, center_score, d_max: float, eps1: float,
                eps2: float):  # noqa: D102
        n = len(embedding)
        emb_sq = (embedding * embedding).sum(dim=-1)
        xyz_sq = (xyz * xyz).sum(dim=-1)
        grad = torch.zeros_like(embedding)
        total = embedding.new_zeros(())
        count = 0
        limit = (2.0 * d_max) ** 2
        for lo in range(0, n, _CHUNK):
            hi = min(lo + _CHUNK, n)
            own = hi - lo                       # columns lo..hi: the chunk's own square
            cols = slice(lo, n)
            # weights: VDM x ASM, and the same-instance mask
            weight = (center_score[lo:hi, None] + center_score[None, cols]).clamp_max_(1.0)
            far = torch.addmm(xyz_sq[None, cols], xyz[lo:hi], xyz[cols].T, alpha=-2.0)
            far = far.add_(xyz_sq[lo:hi, None]) >= limit
            near_pairs = far.numel() - int(far.sum())
            count += 2 * near_pairs - (own * own - int(far[:, :own].sum()))
            weight.masked_fill_(far, 0.0)
            same = (instance[lo:hi, None] == instance[None, cols]) & (instance[lo:hi, None] > 0)
            # D_F and the hinge: t = D - eps1 (same) or eps2 - D (different), kappa = max(0, t)
            dist = torch.addmm(emb_sq[None, cols], embedding[lo:hi], embedding[cols].T, alpha=-2.0)
            dist.add_(emb_sq[lo:hi, None]).clamp_min_(0.0).add_(_SQRT_EPS).sqrt_()
            t = torch.where(same, dist - eps1, eps2 - dist)
            active = t > 0
            weighted = weight * t.clamp_min_(0.0)
            total += 2.0 * weighted.sum() - weighted[:, :own].sum()
            # G = W * sign * [t > 0] / (2 D), sign +1 same, -1 different (the 1/2 is in the 4 -> 2)
            g = torch.where(same, weight, -weight).masked_fill_(~active, 0.0).div_(dist)
            grad[lo:hi] += 2.0 * (g.sum(dim=1, keepdim=True) * embedding[lo:hi] - g @ embedding[cols])
            after = g[:, own:]                  # pairs (chunk row, later row): their later rows
            grad[hi:] += 2.0 * (after.sum(dim=0)[:, None] * embedding[hi:] - after.T @ embedding[lo:hi])
        count = max(count, 1)
        ctx.save_for_backward(grad / count)
        return total / count

    @staticmethod
    def backward(ctx, grad_output):  # noqa: D102
        (grad,) = ctx.saved_tensors
        return grad_output * grad, None, None, None, None, None, None


def embedding_loss_fast(embedding: torch.Tensor, xyz: torch.Tensor, instance: torch.Tensor,
                        center_score: torch.Tensor, d_max: float, eps1: float = EPS1,
                        eps2: float = EPS2) -> torch.Tensor:
    """``embedding_loss`` (same value and gradient, tested) without N x N autograd graphs; the
    one training uses. Gradients flow to ``embedding`` only (the rest is ground truth)."""
    return _EmbeddingLoss.apply(embedding, xyz.to(embedding.dtype), instance,
                                center_score.to(embedding.dtype), float(d_max), eps1, eps2)


def batch_loss(embedding: torch.Tensor, center_score: torch.Tensor, batch: dict[str, torch.Tensor],
               alpha: float = ALPHA, eps1: float = EPS1, eps2: float = EPS2,
               prototype: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(L, L_EF, L_CS) of a collated batch (see dataset.collate): L_EF averaged over blocks,
    L_CS over all real points; padded rows (``valid`` False) are left out of both. With
    ``prototype`` > 0, L_EF also holds that weight times :func:`prototype_loss`."""
    valid = batch["valid"]
    ef_terms = []
    for b in range(embedding.shape[0]):
        rows = valid[b]
        emb, inst, score = embedding[b][rows], batch["instance"][b][rows], batch["center_score"][b][rows]
        term = embedding_loss_fast(emb, batch["xyz"][b][rows], inst, score,
                                   float(batch["part_radius"][b]), eps1, eps2)
        if prototype > 0:
            term = term + prototype * prototype_loss(emb, inst, score)
        ef_terms.append(term)
    loss_ef = torch.stack(ef_terms).mean()
    loss_cs = center_loss(center_score[valid], batch["center_score"][valid])
    return total_loss(loss_ef, loss_cs, alpha), loss_ef, loss_cs
