"""The MoGaF group-wise motion forecaster (paper Sec. "Group-wise Motion
Forecasting", supplementary "Group-wise Motion Forecasting").

One small transformer per motion group. Every Gaussian of the group is one
training sequence: the first T-1 observed poses are the input, the T-th the
target (main paper, "Training Objectives"). Poses are x_t = [mu_t, q_t] in R^7
(supp. "Architecture Details"), after quaternion sign continuity and a
per-sequence instance normalisation (RevIN-style; supp.: "instance
normalization for each sequence"). Inference is an autoregressive rollout
whose window always holds the latest T-1 poses (supp. Fig. "Overview of the
forecaster", (b)).

Choices where the paper is silent (each a parameter, see DEFAULTS):
  * Training data: exactly one window per Gaussian (frames 1..T-1 -> T); the
    paper trains on "the discrepancy ... at time T" only, so no other windows.
    A rigid group's sequences are near copies after instance normalisation,
    so the fit then holds about one example and learns mostly the normalised
    level of the next pose: exact for constant velocity, wrong where the
    motion accelerates (a thrown sphere past its apex is rolled upwards).
  * Masking: a contiguous span of round(r * (T-1)) input frames at a random
    position is replaced by a learned [MASK] embedding (after the linear
    embedding, before positions are added); r goes linearly 0.4 -> 0 over the
    first half of training, the second half is unmasked like inference.
  * Loss space: L_pred and L_acc are evaluated on the instance-normalised
    state the network predicts (per sequence and channel (x - mean) / std of
    the input window). L_acc is affine in mu, so this is the paper's L_acc
    divided by the sequence's std; both terms keep the same units, so
    lambda_acc = 1 keeps its meaning. In world units ("pose") large, slow
    sequences dominate the loss and fit 2-3x worse in our tests.
  * Quaternions are renormalised (and kept sign-continuous) after every
    predicted step, before they re-enter the window.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mogaf.forecast import quat
from mogaf.forecast.base import Forecaster, flush_denormals, torch_determinism
from mogaf.forecast.mogaf_settings import MogafRun, load_run
from mogaf.forecast.params import MOGAF_DEFAULTS
from mogaf.forecast.structured import StructuredMoGaF
from mogaf.forecast.transformer_net import _build_model, mask_ratio, minibatches, optimiser_step, span_masks
from mogaf.progress import Progress


def batch_for_window(batch_size: int, batch_tokens: int, window: int) -> int:
    """Sequences per step: a fixed token budget, capped at batch_size, at least 16 (or batch_size if smaller)."""
    if batch_tokens <= 0:
        return batch_size
    return min(batch_size, max(16, batch_tokens // max(window, 1)))


def instance_norm(window: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sequence and channel mean/std over the window (float64).
    std = sqrt(var + eps): a static channel maps to 0 instead of 0/0."""
    mean = window.mean(axis=1, keepdims=True)
    std = np.sqrt(window.var(axis=1, keepdims=True) + eps)
    return (window - mean) / std, mean[:, 0], std[:, 0]


class MoGaFForecaster(Forecaster):
    """The paper's lightweight (LW) forecaster (forecast.mogaf, `mode: paper`);
    `num_layers: 5` gives HC. The method `mogaf` runs it in paper mode only:
    for_settings gives the structured forecaster otherwise."""

    NAME = "mogaf"
    DEFAULTS: dict[str, Any] = MOGAF_DEFAULTS  # forecast.params.MogafSettings
    FIXED: dict[str, Any] = {}  # settings this class fixes, whatever the section says
    MIN_FRAMES = 3  # L_acc needs mu_{T-1} and mu_{T-2} inside the input window

    @classmethod
    def load_settings(cls, params: Any) -> MogafRun:
        return load_run(cls.NAME, cls.DEFAULTS, params, cls.FIXED)

    @classmethod
    def for_settings(cls, settings: MogafRun) -> type[Forecaster]:
        """forecast.mogaf.mode picks the forecaster, here only: 'structured'
        (mogaf.forecast.structured) or 'paper' (this class)."""
        return StructuredMoGaF if settings.net.mode == "structured" else cls

    def mask_ratio(self, it: int) -> float:
        """Masked fraction of the input window at iteration `it` (linear anneal)."""
        return mask_ratio(self.settings.net, it)

    def _fit(self, obs: np.ndarray) -> None:
        import torch

        from mogaf.optim import Adam

        p = self.settings.net
        g, t, _ = obs.shape
        window = t - 1
        self.window = window
        xin = obs[:, :window]
        target = obs[:, window]
        xn, mean, std = instance_norm(xin, p.norm_eps)

        dev = self.device
        with torch_determinism(self.seed, p.num_threads or None, dev), flush_denormals(dev):
            # the sampling generator stays on the CPU: the same draws on every device
            gen = torch.Generator().manual_seed(self.seed)
            model = _build_model(window, p).to(dev)  # built on the CPU: the same initial weights on every device
            X = torch.from_numpy(xn).float().to(dev)
            M = torch.from_numpy(mean).float().to(dev)
            S = torch.from_numpy(std).float().to(dev)
            Y = torch.from_numpy(target).float().to(dev)
            Yn = torch.from_numpy((target - mean) / std).float().to(dev)
            normalized_loss = p.loss_space == "normalized"
            mu1 = torch.from_numpy(obs[:, window - 1, :3]).float().to(dev)
            mu2 = torch.from_numpy(obs[:, window - 2, :3]).float().to(dev)
            opt = Adam(model.parameters(), lr=p.lr, weight_decay=p.weight_decay)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=p.iterations, eta_min=p.lr_min)
            bs = min(batch_for_window(p.batch_size, p.batch_tokens, window), g)
            model.train()
            loss_val = float("nan")
            pred_val = acc_val = float("nan")
            bar = Progress("forecast.mogaf fit", p.iterations)
            for it, idx in minibatches(g, bs, p.iterations, gen):
                idx = idx.to(dev)
                x = X[idx]
                mask = None
                span = int(round(self.mask_ratio(it) * window))
                if span > 0:
                    mask = span_masks(bs, window, span, window, gen, dev)
                out = model(x, mask)  # normalised prediction of x_T
                if normalized_loss:
                    # Both terms in the instance-normalised representation (the
                    # state the network reads and writes); L_acc is affine in mu,
                    # so this is the paper's L_acc divided by the sequence's std.
                    l_pred = ((out - Yn[idx]) ** 2).sum(-1).mean()
                    acc = out[:, :3] - 2.0 * X[idx, -1, :3] + X[idx, -2, :3]
                else:
                    out = out * S[idx] + M[idx]
                    l_pred = ((out - Y[idx]) ** 2).sum(-1).mean()
                    acc = out[:, :3] - 2.0 * mu1[idx] + mu2[idx]
                l_acc = (acc**2).sum(-1).mean()
                loss = l_pred + p.lambda_acc * l_acc
                optimiser_step(loss, model, opt, sched, p.grad_clip, it)
                loss_val, pred_val, acc_val = loss.item(), l_pred.item(), l_acc.item()
                bar.update(it + 1, loss=loss_val)
            bar.close()
            model.eval()
        self.model = model
        self.info.update(
            final_loss=loss_val,
            final_loss_pred=pred_val,
            final_loss_acc=acc_val,
            iterations=p.iterations,
            epochs=p.iterations * bs / g,
            batch_size=bs,
            window=window,
            num_layers=p.num_layers,
            masking=p.masking,
            n_params=int(sum(v.numel() for v in model.parameters())),
        )

    def predict_next(self, window: np.ndarray) -> np.ndarray:
        """One step: (G, T-1, 7) float64 poses -> (G, 7) next pose (unit quaternion)."""
        import torch

        p = self.settings.net
        xn, mean, std = instance_norm(window, p.norm_eps)
        out = np.empty((window.shape[0], 7))
        chunk = p.rollout_chunk
        with torch.no_grad():
            for s in range(0, window.shape[0], chunk):
                y = self.model(torch.from_numpy(xn[s : s + chunk]).float().to(self.device)).cpu().double().numpy()
                out[s : s + chunk] = y
        out = out * std + mean
        q = quat.normalize(out[:, 3:])
        out[:, 3:] = quat.align_to(q, window[:, -1, 3:])
        return out

    def _rollout(self, n_steps: int) -> np.ndarray:
        p = self.settings.net
        win = self._obs[:, -self.window :].copy()
        out = np.empty((win.shape[0], n_steps, 7))
        with torch_determinism(self.seed, p.num_threads or None, self.device), flush_denormals(self.device):
            for k in range(n_steps):
                nxt = self.predict_next(win)
                out[:, k] = nxt
                win = np.concatenate([win[:, 1:], nxt[:, None]], axis=1)
        return out


class MoGaFPaperForecaster(MoGaFForecaster):
    """The paper's forecaster beside the default one: MoGaF's settings with
    `mode: paper`, whatever forecast.mogaf.mode says ("MoGaF (paper)" in tables)."""

    NAME = "mogaf_paper"
    DEFAULTS = {**MOGAF_DEFAULTS, "mode": "paper"}
    FIXED = {"mode": "paper"}
