"""Motion-aware Gaussian grouping (supplementary Algorithm 3).

Stage 1  seed at the first keyframe: for every mask identity k, the front
         Gaussians whose deformed centre projects into M_k (core.mask_gaussians,
         closest 40 % per image cell).
Stage 2  for every further keyframe in stride order:
         (A) feature-space region growing until no group changes:
             eps_k = alpha * mean over g in G_k of the mean distance from f_g
             to its KNN_K within G_k; every unassigned g' closer than eps_k to
             some member joins G_k (groups in identity order, the unassigned
             set shrinking after each group as in the algorithm);
         (B) seeding at the keyframe: the front Gaussians of each mask join
             their identity's group.
         A last growing pass follows the last seeding, so the seeds of the
         last keyframe propagate too.
Stage 2' (mask_majority, not in the paper) every Gaussian that was a front
         Gaussian of some mask at the keyframes takes the identity given by
         over half of those masks (mask_majority_identity).
Stage 3  KNN voting for the Gaussians still unassigned (voting.py).

Feature: f_g = [canonical mean, pca_scale * PCA(motion coefficients)], with
the PCA fitted on the motion coefficients (softmax of the logits) of all
foreground (dynamic) Gaussians; the number of components is
`pca_components`, or, if None, the fewest whose cumulative explained
variance reaches `pca_explained_variance`. Means are used in scene units,
as in the paper.

Conflicts (memory bank as in Gaga): a Gaussian belongs to at most one group
and keeps the first group it joins, so a Gaussian seeded by a mask at a
later keyframe, or grown into by a second group, stays where it was. Within
one keyframe a Gaussian projects to one pixel and hence one mask. With
`reseed_grown`, a front Gaussian of mask k that only region growing had put
in another group moves to k instead (mask evidence over feature-space
growth; this repairs growth that leaked across a contact between objects).
`mask_majority` decides the conflicts once all keyframes are seen instead:
the identity most of a Gaussian's masks gave it wins, whichever came first.

Efficiency: one KD-tree over all features is built once (features do not
change); every member remembers the radius it has been queried with and is
queried again only if its group's eps_k grows beyond it, which gives the
same result as querying every member at every iteration.
"""

from __future__ import annotations

import itertools

import numpy as np
import scipy.linalg
from scipy.spatial import cKDTree

from .core import MaskFrames, frames_in_time_order, mask_gaussians
from .params import load_settings
from .voting import knn_vote

SEED, GROW, VOTE = 0, 1, 2


def principal_components(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PCA of the rows of x (float64): the scores on every component and each
    component's share of the variance, components by decreasing variance, each
    signed so that its largest-magnitude loading is positive. Equal to the bit
    to scikit-learn's PCA(svd_solver="full").fit_transform (tested), without
    its import (about a second of the group stage)."""
    centred = x - x.mean(axis=0)
    u, s, vt = scipy.linalg.svd(centred, full_matrices=False)
    u *= np.sign(vt[np.arange(vt.shape[0]), np.argmax(np.abs(vt), axis=1)])
    variance = s**2 / (x.shape[0] - 1)
    return u * s, variance / variance.sum()


def motion_features(model, params: dict) -> tuple[np.ndarray, dict]:
    """f_g = [canonical mean, scale * PCA-reduced motion coefficients]."""
    params = load_settings(params)
    means = np.asarray(model.fg.means, dtype=np.float64)
    N = means.shape[0]
    info: dict = {"pca_components": 0, "pca_explained_variance": 0.0}
    if N < 2 or model.motion_coef_logits.shape[1] < 2:
        return means.copy(), info
    coefs = np.asarray(model.motion_coefs(), dtype=np.float64)
    var = coefs.var(axis=0).sum()
    if not np.isfinite(var) or var <= 1e-20:
        return means.copy(), info
    max_c = min(coefs.shape[1], N)
    reduced, ratios = principal_components(coefs)  # max_c components
    if params.pca_components is not None:
        n = int(min(max(int(params.pca_components), 0), max_c))
    else:
        cum = np.cumsum(ratios)
        n = int(np.searchsorted(cum, float(params.pca_explained_variance) - 1e-12) + 1)
        n = min(n, max_c)
    info = {"pca_components": n, "pca_explained_variance": float(ratios[:n].sum())}
    feats = np.concatenate([means, float(params.pca_scale) * reduced[:, :n]], axis=1)
    return feats, info


class _Radius:
    """eps_k = alpha * mean over members of the mean distance to KNN_K members."""

    def __init__(self, features: np.ndarray, params: dict):
        params = load_settings(params)
        self.features = features
        self.alpha = float(params.grow_alpha)
        self.k = int(params.grow_knn)
        self.max_sample = int(params.grow_radius_sample)
        # A fixed random priority per Gaussian: the sampled members change
        # little as a group grows, so eps_k does not jitter.
        self.priority = np.random.default_rng(int(params.seed)).permutation(features.shape[0])
        self.fallback = self._radius(np.arange(features.shape[0]))

    def _radius(self, members: np.ndarray) -> float:
        n = members.size
        if n < 2:
            return 0.0
        k = min(self.k, n - 1)
        pts = self.features[members]
        tree = cKDTree(pts)
        if n > self.max_sample:
            sample = np.argsort(self.priority[members], kind="stable")[: self.max_sample]
            q = pts[sample]
        else:
            q = pts
        d, _ = tree.query(q, k=k + 1)
        return self.alpha * float(d[:, 1:].mean())

    def __call__(self, members: np.ndarray) -> float:
        if members.size < 2:
            return self.fallback
        return self._radius(members)


def region_grow(
    features: np.ndarray,
    tree: cKDTree,
    labels: np.ndarray,
    n_groups: int,
    radius: _Radius,
    queried: np.ndarray,
    stage: np.ndarray,
    max_iters: int,
) -> int:
    """Grow every group until no group changes; labels modified in place.

    Returns the number of iterations.
    """
    it = 0
    changed = True
    # A group only gains members here, so an unchanged count is an unchanged set
    # and its radius (a k-d tree over the members) stays what it was.
    known: dict[int, tuple[int, float]] = {}
    while changed and it < max_iters:
        changed = False
        it += 1
        for k in range(n_groups):
            members = np.flatnonzero(labels == k)
            if members.size == 0:
                continue
            if known.get(k, (-1, 0.0))[0] != members.size:
                known[k] = (members.size, radius(members))
            eps = known[k][1]
            if not (eps > 0.0):
                continue
            need = members[queried[members] < eps]
            if need.size == 0:
                continue
            queried[need] = eps
            hits = tree.query_ball_point(features[need], r=eps)
            flat = np.fromiter(itertools.chain.from_iterable(hits), dtype=np.int64)
            if flat.size == 0:
                continue
            cand = np.unique(flat)
            cand = cand[labels[cand] < 0]
            if cand.size == 0:
                continue
            # Strict "< eps" as in the algorithm (the ball query is inclusive).
            d = _nearest_distance(features, need, cand)
            cand = cand[d < eps]
            if cand.size:
                labels[cand] = k
                stage[cand] = GROW
                changed = True
    return it


def _nearest_distance(features: np.ndarray, sources: np.ndarray, targets: np.ndarray) -> np.ndarray:
    d, _ = cKDTree(features[sources]).query(features[targets], k=1)
    return np.asarray(d)


def seed(
    labels: np.ndarray, stage: np.ndarray, idx: np.ndarray, inst: np.ndarray, queried: np.ndarray | None = None
) -> int:
    """Front Gaussians join their mask's group. Unassigned ones always; with
    `queried` given (reseed_grown), also those that only region growing had
    put in another group, and their growth radius cache is reset so they grow
    for their new group. A Gaussian seeded by a mask keeps its first group."""
    free = labels[idx] < 0
    if queried is not None:
        moved = (stage[idx] == GROW) & (labels[idx] != inst)
        queried[idx[moved]] = 0.0
        free |= moved
    labels[idx[free]] = inst[free]
    stage[idx[free]] = SEED
    return int(free.sum())


def mask_majority_identity(labels: np.ndarray, stage: np.ndarray, votes: np.ndarray) -> int:
    """Give each Gaussian the identity that over half of its mask votes name
    (votes (N, J): how many keyframes' masks took it as a front Gaussian of
    identity j); a Gaussian without such a majority keeps its label. labels
    and stage are modified in place (a moved Gaussian is a seed of its new
    group). Returns how many Gaussians changed group."""
    total = votes.sum(axis=1)
    best = np.argmax(votes, axis=1)
    decided = 2 * votes[np.arange(votes.shape[0]), best] > total
    moved = decided & (labels != best)
    labels[moved] = best[moved]
    stage[moved] = SEED
    return int(moved.sum())


def keyframe_order(time_index: np.ndarray, stride: int) -> np.ndarray:
    return frames_in_time_order(time_index)[:: max(int(stride), 1)]


def group_ours(
    model,
    masks: np.ndarray,
    frames: MaskFrames,
    instance_ids: np.ndarray,
    params: dict,
    frame_order: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Labels (N,) indexing instance_ids (one group per identity), assignment
    stage per Gaussian (0 seed, 1 grow, 2 vote, -1 none) and diagnostics."""
    params = load_settings(params)
    N = len(model.fg)
    J = len(instance_ids)
    labels = np.full(N, -1, dtype=np.int64)
    stage = np.full(N, -1, dtype=np.int8)
    feats, info = motion_features(model, params)
    order = (
        keyframe_order(frames.time_index, params.keyframe_stride) if frame_order is None else np.asarray(frame_order)
    )
    traj = model.trajectory_means
    diag: dict = {**info, "keyframes": [int(f) for f in order], "grow_iterations": [], "seeded": []}
    if N == 0 or J == 0 or order.size == 0:
        return labels, stage, diag
    tree = cKDTree(feats)
    radius = _Radius(feats, params)
    queried = np.zeros(N)
    max_iters = int(params.grow_max_iters)
    votes = np.zeros((N, J), np.int64) if params.mask_majority else None

    def seed_at(f: int, count_votes: bool = True) -> None:
        idx, inst = mask_gaussians(
            np.asarray(traj[:, frames.time_index[f]], dtype=np.float64),
            masks[f],
            frames.K[f],
            frames.w2c[f],
            instance_ids,
            float(params.front_fraction),
            int(params.front_patches),
        )
        if votes is not None and count_votes:
            votes[:] += np.bincount(idx * J + inst, minlength=N * J).reshape(N, J)
        diag["seeded"].append(seed(labels, stage, idx, inst, queried if params.reseed_grown else None))

    def grow() -> None:
        diag["grow_iterations"].append(region_grow(feats, tree, labels, J, radius, queried, stage, max_iters))

    seed_at(int(order[0]))
    if params.grow_after_last_keyframe:
        # ours: grow, seed the next keyframe; and grow once more after the last one
        for f in order[1:]:
            grow()
            seed_at(int(f))
        grow()
    else:
        # Algorithm 3: every keyframe in turn, the first again, grows and then seeds; then the vote
        for i, f in enumerate(order):
            grow()
            seed_at(int(f), count_votes=i > 0)
    if votes is not None:
        diag["mask_majority_moved"] = mask_majority_identity(labels, stage, votes)
    before = labels < 0
    labels, rounds = knn_vote(feats, labels, int(params.vote_knn), float(params.vote_fraction))
    stage[before & (labels >= 0)] = VOTE
    diag["vote_rounds"] = rounds
    return labels, stage, diag
