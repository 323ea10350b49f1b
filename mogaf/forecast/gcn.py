"""GaussianPrediction-style GCN baseline ("GSPred-SoM" in the MoGaF paper).

Upstream (BoMingZhao/GaussianPrediction, motion_model/gcn.py: GCN_xyzr;
train_GCN.py; options/gaussian_option.py: gcn_training; scripts/predict/*):
the graph nodes are a fixed set of keypoints ("super Gaussians",
--max_points 100) whose trajectories drive all Gaussians through their
nearest keypoints (--nearest_num 6, scene/gaussian_model.py). Two channel-GCNs
with learnable adjacency -- one over the keypoints' xyz channels, one over
their rotation-quaternion channels -- map a window of 10 past frames to the
next frame; prediction is autoregressive.

Our adaptation to per-group trajectory input (no 4DGS deformation field):
  * Control points: farthest point sampling on the first observed frame's
    means (upstream clusters canonical means + learned motion features with
    k-means; we have no motion features). A control point follows the
    trajectory of the Gaussian it sits on; its rotation channel is its
    rotation relative to the first observed frame (upstream feeds keypoint
    rotations relative to canonical).
  * Carrying the motion to all Gaussians: each Gaussian is skinned to its 6
    nearest control points (first-frame distance) with normalised Gaussian
    kernel weights (upstream learns the weights with a hash-grid MLP from the
    photometric loss, which does not exist here). Future poses are linear blend
    skinning of the control points' rigid increments from the last observed
    frame:  mu_g(t) = sum_k w_gk [x_k(t) + dR_k(t) (mu_g(T) - x_k(T))],
            q_g(t) = normalize(sum_k w_gk dq_k(t)) * q_g(T),
    with dq_k(t) = r_k(t) r_k(T)^-1. A uniformly moving rigid group is
    carried exactly, whatever the weights.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from mogaf.errors import MogafError
from mogaf.forecast import quat
from mogaf.forecast.base import Forecaster, epochs_for, torch_determinism
from mogaf.forecast.baseline_params import GCN_DEFAULTS
from mogaf.progress import Progress


def farthest_point_sampling(points: np.ndarray, k: int) -> np.ndarray:
    """Indices of k points by FPS, starting from the point farthest from the
    centroid (deterministic)."""
    n = points.shape[0]
    k = min(k, n)
    idx = np.empty(k, dtype=np.int64)
    d_centre = np.linalg.norm(points - points.mean(0), axis=1)
    idx[0] = int(np.argmax(d_centre))
    dist = np.linalg.norm(points - points[idx[0]], axis=1)
    for i in range(1, k):
        idx[i] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(points - points[idx[i]], axis=1))
    return idx


def skinning_weights(points: np.ndarray, nodes: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """k nearest nodes per point and normalised Gaussian-kernel weights whose
    bandwidth is the point's mean distance to those nodes."""
    k = min(k, nodes.shape[0])
    d2 = ((points[:, None, :] - nodes[None, :, :]) ** 2).sum(-1)
    nn_idx = np.argsort(d2, axis=1, kind="stable")[:, :k]
    nd2 = np.take_along_axis(d2, nn_idx, axis=1)
    sigma2 = np.maximum(nd2.mean(axis=1, keepdims=True), 1e-12)
    w = np.exp(-0.5 * nd2 / sigma2)
    w /= w.sum(axis=1, keepdims=True)
    return nn_idx, w


def _build_model(n_nodes: int, p: dict[str, Any]):
    import math

    import torch
    import torch.nn.functional as F
    from torch import nn

    class GraphConv(nn.Module):
        """y = A (x W) + b with a learnable dense adjacency A (N x N)."""

        def __init__(self, fin: int, fout: int, n: int) -> None:
            super().__init__()
            stdv = 1.0 / math.sqrt(fout)
            self.weight = nn.Parameter(torch.empty(fin, fout).uniform_(-stdv, stdv))
            self.att = nn.Parameter(torch.empty(n, n).uniform_(-stdv, stdv))
            self.bias = nn.Parameter(torch.empty(fout).uniform_(-stdv, stdv))

        def forward(self, x):
            # A (x W) for every window as one product, A (N x N) times the windows'
            # supports side by side (N x B*F): the same sums as one product per
            # window (tests/test_forecast.py), in about 10 % less time per training
            # step than torch.matmul's broadcast over the windows.
            support = torch.matmul(x, self.weight)
            b, n, f = support.shape
            y = torch.mm(self.att, support.transpose(0, 1).reshape(n, b * f))
            return y.view(n, b, f).transpose(0, 1) + self.bias

    class GCBlock(nn.Module):
        """Residual block: (gc -> BN -> tanh -> dropout) x 2, + input."""

        def __init__(self, f: int, n: int, p_drop: float) -> None:
            super().__init__()
            self.gc1, self.gc2 = GraphConv(f, f, n), GraphConv(f, f, n)
            self.bn1, self.bn2 = nn.BatchNorm1d(n * f), nn.BatchNorm1d(n * f)
            self.drop = nn.Dropout(p_drop)

        def _bn(self, bn, y):
            b, n, f = y.shape
            return bn(y.reshape(b, -1)).reshape(b, n, f)

        def forward(self, x):
            y = self.drop(torch.tanh(self._bn(self.bn1, self.gc1(x))))
            y = self.drop(torch.tanh(self._bn(self.bn2, self.gc2(y))))
            return y + x

    class GCN(nn.Module):
        def __init__(self, n: int) -> None:
            super().__init__()
            h = p.linear_size
            self.gc1 = GraphConv(p.input_size, h, n)
            self.bn1 = nn.BatchNorm1d(n * h)
            self.blocks = nn.ModuleList(GCBlock(h, n, p.dropout) for _ in range(p.num_stage))
            if p.no_mapping:
                self.out = GraphConv(h, p.output_size, n)
            else:
                self.out = nn.Sequential(nn.Linear(h, h), nn.ReLU(), nn.Linear(h, p.output_size))
            self.drop = nn.Dropout(p.dropout)

        def forward(self, x):
            y = self.gc1(x)
            b, n, f = y.shape
            y = self.drop(torch.tanh(self.bn1(y.reshape(b, -1)).reshape(b, n, f)))
            for blk in self.blocks:
                y = blk(y)
            return self.out(y)

    class ChannelGCN(nn.Module):
        """One GCN over nodes x channels: (B, C, K, W) -> (B, C, K, out)."""

        def __init__(self, channels: int) -> None:
            super().__init__()
            self.gcn = GCN(n_nodes * channels)

        def forward(self, x):
            b, c, k, _ = x.shape
            return self.gcn(x.reshape(b, c * k, -1)).reshape(b, c, k, -1)

    class GCNxyzr(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.gcn_xyz = ChannelGCN(3)
            self.gcn_r = ChannelGCN(4)

        def forward(self, xyz, r):
            return self.gcn_xyz(xyz), F.normalize(self.gcn_r(r), dim=1)

    return GCNxyzr()


class GCNForecaster(Forecaster):
    NAME = "gcn"
    DEFAULTS = GCN_DEFAULTS  # forecast.baseline_params.GCNSettings
    MIN_FRAMES = 4  # two training windows of at least two frames (BatchNorm needs a batch > 1)

    def _fit(self, obs: np.ndarray) -> None:
        import torch

        from mogaf.optim import Adam

        p = self.settings
        # each setting's own bounds are checked by its settings class (mogaf.forecast.baseline_params)
        g, t, _ = obs.shape
        out_size = p.output_size
        # Window: upstream's 10 frames, clipped so at least two training windows exist.
        w = min(p.input_size, t - out_size - 1)
        if w < 2:
            raise MogafError(f"forecast.gcn: {t} observed frames are too few for output_size {out_size}")
        self.info["window_clipped"] = w != p.input_size
        pw = dataclasses.replace(p, input_size=w)
        self.window = w

        nodes = farthest_point_sampling(obs[:, 0, :3], p.n_nodes)
        k = len(nodes)
        self.nodes = nodes
        self.nn_idx, self.weights = skinning_weights(obs[:, 0, :3], obs[nodes, 0, :3], p.nearest_num)
        xyz = obs[nodes, :, :3].transpose(1, 0, 2)  # (T, K, 3)
        q = obs[nodes, :, 3:]
        r = quat.mul(q, quat.conj(q[:, :1]))  # rotation relative to the first observed frame
        r = quat.make_continuous(r, axis=1).transpose(1, 0, 2)  # (T, K, 4)
        self._xyz_hist, self._r_hist = xyz, r

        n_win = t - w - out_size + 1
        xin = np.stack([xyz[i : i + w] for i in range(n_win)])  # (n, W, K, 3)
        xgt = np.stack([xyz[i + w : i + w + out_size] for i in range(n_win)])
        rin = np.stack([r[i : i + w] for i in range(n_win)])
        rgt = np.stack([r[i + w : i + w + out_size] for i in range(n_win)])

        dev = self.device
        with torch_determinism(self.seed, p.num_threads or None, dev):
            # the sampling generator stays on the CPU: the same draws on every device
            gen = torch.Generator().manual_seed(self.seed)
            model = _build_model(k, pw).to(dev)  # built on the CPU: the same initial weights on every device
            XI = torch.from_numpy(xin).float().permute(0, 3, 2, 1).to(dev)  # (n, 3, K, W)
            RI = torch.from_numpy(rin).float().permute(0, 3, 2, 1).to(dev)
            XG = torch.from_numpy(xgt).float().to(dev)  # (n, out, K, 3)
            RG = torch.from_numpy(rgt).float().to(dev)
            opt = Adam(model.parameters(), lr=p.lr, eps=p.adam_eps)
            # drop_last as upstream; with fewer windows than a batch, one batch of all.
            bs = min(p.batch_size, n_win)
            epochs = epochs_for(p.epochs, p.steps, n_win // bs)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs, eta_min=p.lr_min)
            model.train()
            loss_val = float("nan")
            bar = Progress("forecast.gcn epoch", epochs)
            for epoch in range(epochs):
                noise = p.noise_init * max(1.0 - epoch / p.noise_step, 0.0) if p.noise_init > 0 else 0.0
                perm = torch.randperm(n_win, generator=gen)
                tot, nb = 0.0, 0
                for s in range(0, n_win - bs + 1, bs):
                    idx = perm[s : s + bs].to(dev)
                    xi, ri = XI[idx], RI[idx]
                    if noise > 0:
                        xi = xi + ((2 * torch.rand(xi.shape, generator=gen) - 1) * noise).to(dev)
                        ri = torch.nn.functional.normalize(
                            ri + ((2 * torch.rand(ri.shape, generator=gen) - 1) * noise * 0.5).to(dev), dim=1
                        )
                    xp, rp = model(xi, ri)
                    xp = xp.permute(0, 3, 2, 1)  # (B, out, K, 3)
                    rp = rp.permute(0, 3, 2, 1)
                    loss = torch.norm(xp - XG[idx], dim=-1).mean() + torch.norm(rp - RG[idx], dim=-1).mean()
                    if not torch.isfinite(loss):
                        raise MogafError(f"forecast.gcn: training diverged (non-finite loss in epoch {epoch})")
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
                    tot += loss.item()
                    nb += 1
                sched.step()
                loss_val = tot / max(nb, 1)
                bar.update(epoch + 1, loss=loss_val)
            bar.close()
            model.eval()
        self.model = model
        self.info.update(
            final_loss=loss_val,
            epochs=epochs,
            iterations=epochs * (n_win // bs),
            n_nodes=k,
            window=w,
            train_windows=n_win,
            batch_size=bs,
        )

    def _rollout(self, n_steps: int) -> np.ndarray:
        import torch

        p = self.settings
        w, out_size = self.window, p.output_size
        xyz_win = self._xyz_hist[-w:].copy()  # (W, K, 3)
        r_win = self._r_hist[-w:].copy()
        xyz_pred, r_pred = [], []
        with torch_determinism(self.seed, p.num_threads or None, self.device), torch.no_grad():
            made = 0
            while made < n_steps:
                xi = torch.from_numpy(xyz_win[None]).float().permute(0, 3, 2, 1).to(self.device)
                ri = torch.from_numpy(r_win[None]).float().permute(0, 3, 2, 1).to(self.device)
                xp, rp = self.model(xi, ri)
                xp = xp.permute(0, 3, 2, 1)[0].cpu().double().numpy()  # (out, K, 3)
                rp = rp.permute(0, 3, 2, 1)[0].cpu().double().numpy()
                for j in range(out_size):
                    rq = quat.align_to(quat.normalize(rp[j]), r_win[-1])
                    xyz_pred.append(xp[j])
                    r_pred.append(rq)
                    xyz_win = np.concatenate([xyz_win[1:], xp[j][None]])
                    r_win = np.concatenate([r_win[1:], rq[None]])
                made += out_size
        node_xyz = np.stack(xyz_pred[:n_steps])  # (n, K, 3)
        node_r = np.stack(r_pred[:n_steps])  # (n, K, 4)
        return self._skin(node_xyz, node_r)

    def _skin(self, node_xyz: np.ndarray, node_r: np.ndarray) -> np.ndarray:
        """Carry control-point motion (from the last observed frame) to all Gaussians."""
        last = self._obs[:, -1]
        x_last = self._xyz_hist[-1]  # (K, 3)
        r_last = self._r_hist[-1]
        nn_idx, wts = self.nn_idx, self.weights  # (G, k)
        n = node_xyz.shape[0]
        out = np.empty((last.shape[0], n, 7))
        ident = np.array([1.0, 0.0, 0.0, 0.0])
        for s in range(n):
            dq = quat.normalize(quat.mul(node_r[s], quat.conj(r_last)))  # (K, 4) world increment
            dq = quat.align_to(dq, ident)
            dqn = dq[nn_idx]  # (G, k, 4)
            lever = last[:, None, :3] - x_last[nn_idx]  # (G, k, 3)
            moved = node_xyz[s][nn_idx] + quat.rotate(dqn, lever)
            out[:, s, :3] = (wts[..., None] * moved).sum(1)
            blend = (wts[..., None] * dqn).sum(1)
            # Increments more than ~90 degrees apart can cancel; fall back to the
            # nearest control point's increment there.
            weak = np.linalg.norm(blend, axis=-1) < 1e-6
            blend = quat.normalize(np.where(weak[:, None], dqn[:, 0], blend))
            out[:, s, 3:] = quat.normalize(quat.mul(blend, last[:, 3:]))
        return out
