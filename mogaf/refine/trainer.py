"""The refinement trainer: the reconstruction trainer plus L_rigid and L_nr.

neighbour_pairs gives NN(g) for L_nr, rigid_residuals the rigid-fit residual
of the rigid groups (reported before and after refinement); see the
mogaf.refine package docstring for the losses.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..grouping.core import Groups
from ..grouping.stage import rigid_init
from ..optim import Adam
from ..recon.data import TrainData
from ..recon.init_common import InitResult
from ..recon.trainer import Trainer
from ..representation import Model4D, matrix_to_rot6d, rot6d_to_matrix
from ..rigid import apply_rigid


def neighbour_pairs(canonical: np.ndarray, groups: Groups, k: int, radius_factor: float) -> dict[int, np.ndarray]:
    """Per dynamic non-rigid group: (P, 2) global index pairs (g, g') with g' in NN(g)."""
    from scipy.spatial import cKDTree

    out: dict[int, np.ndarray] = {}
    for gid in range(groups.num_groups):
        if groups.rigid[gid] or groups.static[gid]:
            continue
        members = groups.members(gid)
        if members.size < 2:
            continue
        pts = np.asarray(canonical[members], dtype=np.float64)
        tree = cKDTree(pts)
        kk = min(k + 1, members.size)
        dist, idx = tree.query(pts, k=kk)
        nn1 = dist[:, 1]
        positive = nn1[nn1 > 0]
        radius = radius_factor * (float(np.median(positive)) if positive.size else 0.0)
        ok = (dist[:, 1:] <= radius) & (idx[:, 1:] != np.arange(members.size)[:, None])
        rows = np.repeat(np.arange(members.size), kk - 1).reshape(members.size, kk - 1)
        pairs = np.stack([members[rows[ok]], members[idx[:, 1:][ok]]], axis=1).astype(np.int64)
        if pairs.size:
            out[gid] = pairs
    return out


def rigid_residuals(model: Model4D, groups: Groups) -> dict[str, float]:
    """Mean over observed steps of the RMS rigid-fit residual, per rigid group (scene units)."""
    if not np.any(groups.rigid == 1):
        return {}
    fit = rigid_init(model, groups, {})
    return {
        str(int(g)): float(np.mean(r))
        for g, r in zip(fit["group_ids"], fit["residual_rms"])
        if groups.members(int(g)).size > 0
    }


class RefineTrainer(Trainer):
    """The reconstruction trainer plus L_motion, without density control."""

    def __init__(
        self,
        data: TrainData,
        recon_params: dict,
        seed: int,
        groups: Groups,
        rigid: dict | None,
        refine: dict,
        *,
        init: InitResult | None = None,
        state: dict | None = None,
    ):
        super().__init__(data, recon_params, seed, init=init, state=state)
        self.refine = refine
        d = self.dev
        canonical = self.model.fg.get("means").detach().cpu().numpy()
        self.pairs = {
            g: torch.tensor(p, device=d)
            for g, p in neighbour_pairs(canonical, groups, refine["nr_neighbors"], refine["nr_radius_factor"]).items()
        }
        self.rigid_members: dict[int, torch.Tensor] = {}
        self.rigid_rot6d = self.rigid_transl = None
        if rigid is not None and rigid["group_ids"].size:
            gids = [int(g) for g in rigid["group_ids"]]
            self.rigid_index = {g: i for i, g in enumerate(gids)}
            self.rigid_members = {g: torch.tensor(groups.members(g), device=d) for g in gids if groups.members(g).size}
            if state is not None and "rigid" in state:
                r6, tr = state["rigid"]["rot6d"], state["rigid"]["transl"]
            else:
                r6 = matrix_to_rot6d(torch.as_tensor(rigid["rotations"], dtype=torch.float64)).float()
                tr = torch.as_tensor(rigid["translations"], dtype=torch.float32)
            self.rigid_rot6d = torch.nn.Parameter(r6.to(d).clone())
            self.rigid_transl = torch.nn.Parameter(tr.to(d).clone())
            if refine["learn_rigid_motion"]:
                p = self.p
                for name, prm, lr in (
                    ("rigid.rot6d", self.rigid_rot6d, p.lr_rots * p.lr_boost),
                    ("rigid.transl", self.rigid_transl, p.lr_transls * self.scale * p.lr_boost),
                ):
                    self.base_lr[name] = lr
                    self.optimizers[name] = Adam([prm], lr=lr, eps=1e-15)
                    if state is not None and name in state["optimizers"]:
                        self.optimizers[name].load_state_dict(state["optimizers"][name])
            else:
                self.rigid_rot6d.requires_grad_(False)
                self.rigid_transl.requires_grad_(False)
        self.extra_loss = self.motion_loss

    def control(self):  # no densification: the grouped Gaussian set stays as it is
        return None

    def motion_loss(self, pick: torch.Tensor, note) -> torch.Tensor:
        r = self.refine
        total = torch.zeros((), device=self.dev)
        T = self.data.num_timesteps
        if self.rigid_members and r["lambda_rigid"] > 0:
            nt = min(r["rigid_times"], T)
            ts = torch.randperm(T, generator=self.gen)[:nt].to(self.dev)
            loss = torch.zeros((), device=self.dev)
            for g, members in self.rigid_members.items():
                n = int(members.numel())
                if n > r["rigid_members"]:
                    members = members[torch.randperm(n, generator=self.gen)[: r["rigid_members"]].to(self.dev)]
                i = self.rigid_index[g]
                # Phi_t(g) = R_t mu_c + t_t, (nt, n, 3) -> (n, nt, 3) like the learned means
                target = apply_rigid(
                    rot6d_to_matrix(self.rigid_rot6d[i, ts]),
                    self.rigid_transl[i, ts],
                    self.model.fg.get("means")[members],
                ).transpose(0, 1)
                d2 = ((self.model.fg_means_at(ts, members) - target) ** 2).sum(-1) / self.scale**2
                loss = loss + d2.mean(dim=1).sum() * (n / members.numel())
            total = total + r["lambda_rigid"] * note("rigid", loss)
        if self.pairs and r["lambda_nr"] > 0:
            w = self.model.fg.coefs()
            loss = torch.zeros((), device=self.dev)
            for pairs in self.pairs.values():
                loss = loss + ((w[pairs[:, 0]] - w[pairs[:, 1]]) ** 2).sum()
            total = total + r["lambda_nr"] * note("nr", loss)
        return total

    def checkpoint_state(self, digest: str) -> dict[str, Any]:
        state = super().checkpoint_state(digest)
        if self.rigid_rot6d is not None:
            state["rigid"] = {
                "rot6d": self.rigid_rot6d.detach().cpu().clone(),
                "transl": self.rigid_transl.detach().cpu().clone(),
            }
        return state
