"""KNN voting for Gaussians left unassigned (supp. Algorithm 3, Stage 3).

Paper (supp. "Reassignment Strategy"): each unassigned Gaussian votes among
its 8 nearest group-assigned neighbours in feature space; only the closest
50 % of the unassigned Gaussians, by their mean distance to those
neighbours, are reassigned.

Decision for the other half (the paper leaves them open): voting rounds
repeat, each one over the current labelled set (which now includes the
Gaussians labelled in earlier rounds) and relabelling the closest
`fraction` of the still-unassigned ones (at least one), until every
Gaussian has a label. Labels thus spread from the labelled groups outward,
the nearest Gaussians first; about log2(#unassigned) rounds are needed.

Ties in the vote go to the group of the nearest labelled neighbour among
the tied groups; equal mean distances keep index order (stable sort).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def vote_round(features: np.ndarray, labels: np.ndarray, k: int = 8, fraction: float = 0.5) -> np.ndarray:
    """One voting round; returns the indices that received a label.

    labels (N,) int64 with -1 for unassigned, modified in place.
    """
    labelled = np.flatnonzero(labels >= 0)
    unassigned = np.flatnonzero(labels < 0)
    if unassigned.size == 0 or labelled.size == 0:
        return np.zeros(0, dtype=np.int64)
    kk = int(min(k, labelled.size))
    tree = cKDTree(features[labelled])
    dist, nn = tree.query(features[unassigned], k=kk)
    dist = dist.reshape(unassigned.size, kk)
    nn_labels = labels[labelled[nn.reshape(unassigned.size, kk)]]
    n_groups = int(labels.max()) + 1
    votes = np.zeros((unassigned.size, n_groups), dtype=np.float64)
    np.add.at(votes, (np.repeat(np.arange(unassigned.size), kk), nn_labels.ravel()), 1.0)
    # Tie-break: half a vote for the nearest neighbour's group (votes are integers).
    votes[np.arange(unassigned.size), nn_labels[:, 0]] += 0.5
    winner = np.argmax(votes, axis=1)
    mean_dist = dist.mean(axis=1)
    n_take = max(int(np.ceil(fraction * unassigned.size - 1e-9)), 1)
    take = np.argsort(mean_dist, kind="stable")[:n_take]
    labels[unassigned[take]] = winner[take]
    return unassigned[take]


def knn_vote(
    features: np.ndarray, labels: np.ndarray, k: int = 8, fraction: float = 0.5, max_rounds: int | None = None
) -> tuple[np.ndarray, int]:
    """Repeat vote_round until every Gaussian is labelled (or max_rounds).

    Returns (labels, number of rounds). If nothing is labelled, nothing
    changes.
    """
    labels = np.asarray(labels, dtype=np.int64).copy()
    features = np.asarray(features, dtype=np.float64)
    rounds = 0
    while np.any(labels < 0) and np.any(labels >= 0):
        if max_rounds is not None and rounds >= max_rounds:
            break
        vote_round(features, labels, k, fraction)
        rounds += 1
    return labels, rounds
