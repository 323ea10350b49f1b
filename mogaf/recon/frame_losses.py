"""Per-frame loss terms of the reconstruction trainer (mixed into Trainer).

The 2D track loss (the fg Gaussians' 3D positions at target frames, rendered
at a tracked pixel, projected into the target frames and compared with the
2D tracks) and the silhouette loss (forward + coverage terms between the
projected fg centres and the masks, see silhouette.py).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .losses import masked_l1
from .silhouette import project_batch


class FrameLosses:
    """The track and silhouette terms Trainer.step adds per sampled frame."""

    def silhouette_loss(self, f: int, means: torch.Tensor) -> torch.Tensor:
        frames = torch.tensor([f], device=self.dev)
        uv, front = project_batch(means[:, None], self.K[frames], self.w2c[frames], 1e-3 * self.scale)
        labels = self.model.fg.aux.get("labels")
        fwd, cov = self.sil.terms(frames, uv, front, self.model.fg.opacities().detach(), labels)
        return fwd + cov

    def track_loss(
        self, f: int, targets: torch.Tensor, feats: torch.Tensor, acc: torch.Tensor, q: float
    ) -> torch.Tensor:
        off = 4 if self.has_bg else 3
        vis_f = self.tracks_vis[:, f]
        xy_f = self.tracks_xy[:, f]
        inb = vis_f & (xy_f[:, 0] >= 0) & (xy_f[:, 1] >= 0) & (xy_f[:, 0] < self.W) & (xy_f[:, 1] < self.H)
        # fg tracks only (the points the dynamic Gaussians must follow)
        idx = torch.nonzero(inb, as_tuple=False).squeeze(1)
        if idx.numel() == 0:
            return feats.sum() * 0.0
        px = xy_f[idx]
        fgv = self.masks[f][px[:, 1].long().clamp(0, self.H - 1), px[:, 0].long().clamp(0, self.W - 1)]
        idx, px = idx[fgv > 0.5], px[fgv > 0.5]
        if idx.numel() == 0:
            return feats.sum() * 0.0
        grid = torch.stack([px[:, 0] / self.W * 2 - 1, px[:, 1] / self.H * 2 - 1], -1).reshape(1, 1, -1, 2)
        k = len(targets)
        maps = torch.cat([feats[..., off : off + 3 * k], acc], -1).permute(2, 0, 1)[None]
        s = F.grid_sample(maps, grid, mode="bilinear", align_corners=False)[0, :, 0].T  # (M, 3k+1)
        pts = s[:, : 3 * k].reshape(-1, k, 3) / s[:, -1:].clamp_min(1e-4)[:, None]
        losses = []
        weights = []
        T = self.data.num_timesteps
        preds, gts, ws = [], [], []
        for j, g in enumerate(targets.tolist()):
            P = pts[:, j]
            cam = P @ self.w2c[g][:3, :3].T + self.w2c[g][:3, 3]
            uvw = cam @ self.K[g].T
            uv = uvw[:, :2] / uvw[:, 2:3].clamp_min(1e-6)
            vis_g = self.tracks_vis[idx, g].float()
            wint = math.exp(-2.0 * abs(int(self.tidx[f]) - int(self.tidx[g])) / T)
            preds.append(uv)
            gts.append(self.tracks_xy[idx, g])
            ws.append(vis_g * wint)
        del losses, weights
        pred = torch.cat(preds)
        gt = torch.cat(gts)
        w = torch.cat(ws)[:, None]
        return masked_l1(pred, gt, w, q) / max(self.H, self.W)
