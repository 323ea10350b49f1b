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

import math
import time
from typing import Any

import numpy as np

from mogaf.errors import MogafError
from mogaf.forecast import quat
from mogaf.forecast.base import Forecaster, torch_determinism
from mogaf.forecast.structured import MODES, STRUCTURED_DEFAULTS, fit_structured, structured_params

DEFAULTS: dict[str, Any] = {
    # --- mode: "structured" (the default, mogaf.forecast.structured) or "paper" (this module's
    # forecaster exactly as the paper describes it; config/paper.yaml, "MoGaF (paper)" in tables) ---
    "mode": "structured",
    "structured": dict(STRUCTURED_DEFAULTS),  # the structured mode's own settings (the paper mode ignores them)
    # --- architecture: supp. "Architecture Details" / main Sec. 4.1 "Implementation Details" ---
    "d_model": 32,  # "32-dimensional hidden state"
    "nhead": 8,  # "eight attention heads"
    "dim_feedforward": 64,  # "64-dimensional feedforward layer"
    "dropout": 0.2,  # "We apply a dropout rate of 0.2" (residual branches and feed-forward)
    "num_layers": 1,  # "single-layer Transformer encoder" (LW); 5 = HC (supp. "Effect of Forecaster Capacity")
    # not stated in the paper (ours):
    "attn_dropout": 0.0,  # no dropout on attention weights (PatchTST's default; its RevIN + flatten-head design matches)
    "norm_first": True,  # pre-norm: keeps a linear path from the normalised inputs to the flatten head
    "zero_init_residual": True,  # attention/FFN branches start at zero, i.e. training starts from a linear autoregressor
    # --- state normalisation: supp. "use instance normalization for each sequence" ---
    "norm_eps": 1e-5,  # variance floor (RevIN's eps): std = sqrt(var + eps), so static sequences stay finite
    # --- objective: main "Training Objectives", supp. "Training Procedure and Inference Scheme" ---
    "lambda_acc": 1.0,  # "lambda_acc = 1.0 for all experiments"
    "loss_space": "normalized",  # L_pred and L_acc on the instance-normalised state ("pose": world units); see module doc
    # --- masked input training: main "Masked Input Training", supp. "Training Procedure" ---
    "masking": True,  # False = the "w/o masking" ablation (main Table "Ablation results", bottom)
    "mask_ratio_start": 0.4,  # "a contiguous span covering 40--0% of the sequence is masked"
    "mask_ratio_end": 0.0,
    "mask_anneal_frac": 0.5,  # ours: linear 40% -> 0% over the first half of training, unmasked after
    # --- optimisation: not in the paper; ours, sized for <= 60 s per group on 2 CPU cores ---
    "iterations": 800,  # Adam steps; cost does not grow with the group size: ~20 s CPU at 1 thread for T = 36
    # (~28 s for T = 48), leaving ~2-3x headroom under the 60 s/group budget on a loaded 2-core machine
    "batch_size": 128,  # most Gaussians per step, drawn without replacement (epochs = iterations * batch / G)
    "batch_tokens": 4480,  # pose tokens per step: batch = min(batch_size, batch_tokens // (T-1)), at least 16;
    # 4480 = 128 x 35 (T = 36). Attention costs ~ batch x (T-1)^2, so long sequences take smaller batches
    # and the step cost grows ~linearly in T instead of quadratically (0 = always batch_size)
    "lr": 5e-3,
    "lr_min": 1e-5,  # cosine decay floor
    "weight_decay": 0.03,  # L2 on all weights (Adam). A group's sequences are near copies after instance
    # normalisation, so one-target training is under-determined; without decay the free directions of the
    # flatten head make the autoregressive rollout blow up (GT benchmark, ratio 0.6: default/sphere 1.55 -> 0.39 m,
    # hard/box_extra_1 1.87 -> 0.11 m). 0.1 damps further but bends periodic motion (circular test 3% -> 15%)
    "grad_clip": 1.0,  # global grad-norm clip
    # --- runtime ---
    "num_threads": 1,  # tiny tensors: one intra-op thread is as fast and never oversubscribes parallel jobs (0 = torch's default)
    "rollout_chunk": 16384,  # Gaussians per forward pass at inference
}


def _sinusoid(length: int, dim: int):
    import torch

    pos = torch.arange(length, dtype=torch.float32)[:, None]
    i = torch.arange(0, dim, 2, dtype=torch.float32)
    div = torch.exp(-math.log(10000.0) * i / dim)
    pe = torch.zeros(length, dim)
    pe[:, 0::2] = torch.sin(pos * div)
    pe[:, 1::2] = torch.cos(pos * div[: pe[:, 1::2].shape[1]])
    return pe


def _build_model(window: int, p: dict[str, Any], in_dim: int = 7, out_dim: int = 7, zero_head: bool = False):
    import torch
    import torch.nn.functional as F
    from torch import nn

    class EncoderLayer(nn.Module):
        """Post-norm transformer encoder layer (same maths as
        torch.nn.TransformerEncoderLayer, relu feed-forward), written out so
        attention can run through scaled_dot_product_attention. Dropout acts on
        the residual branches and the feed-forward; dropout on the attention
        weights is separate (`attn_dropout`, 0 as in PatchTST)."""

        def __init__(self, d: int, nhead: int, dim_ff: int, dropout: float, attn_dropout: float, norm_first: bool) -> None:
            super().__init__()
            self.nhead = nhead
            self.qkv = nn.Linear(d, 3 * d)
            self.proj = nn.Linear(d, d)
            self.ff1 = nn.Linear(d, dim_ff)
            self.ff2 = nn.Linear(dim_ff, d)
            self.norm1 = nn.LayerNorm(d)
            self.norm2 = nn.LayerNorm(d)
            self.p_drop = dropout
            self.attn_dropout = attn_dropout
            self.norm_first = norm_first

        def drop(self, x):
            # Inverted dropout from a uniform draw: same distribution as
            # nn.Dropout, but torch.rand is much cheaper than bernoulli_ on CPU.
            if not self.training or self.p_drop <= 0.0:
                return x
            keep = torch.rand_like(x) >= self.p_drop
            return x * keep / (1.0 - self.p_drop)

        def forward(self, x):
            b, n, d = x.shape
            h = self.norm1(x) if self.norm_first else x
            q, k, v = self.qkv(h).view(b, n, 3, self.nhead, d // self.nhead).permute(2, 0, 3, 1, 4)
            a = F.scaled_dot_product_attention(q, k, v, dropout_p=self.attn_dropout if self.training else 0.0)
            a = a.transpose(1, 2).reshape(b, n, d)
            if self.norm_first:
                x = x + self.drop(self.proj(a))
                h = self.norm2(x)
                return x + self.drop(self.ff2(self.drop(F.relu(self.ff1(h)))))
            x = self.norm1(x + self.drop(self.proj(a)))
            return self.norm2(x + self.drop(self.ff2(self.drop(F.relu(self.ff1(x))))))

    class MotionTransformer(nn.Module):
        """Linear embedding in_dim -> d (+ sinusoidal positions), encoder, flatten head -> out_dim
        (7 -> 7 in the paper's mode; 1 -> horizon in the structured mode)."""

        def __init__(self) -> None:
            super().__init__()
            d = p["d_model"]
            self.embed = nn.Linear(in_dim, d)
            # Learned [MASK] embedding replacing masked frames (BERT-style, the
            # paper's cited inspiration for masked motion modelling).
            self.mask_token = nn.Parameter(torch.randn(d) * 0.02)
            self.register_buffer("pos", _sinusoid(window, d), persistent=False)
            self.layers = nn.ModuleList(
                EncoderLayer(d, p["nhead"], p["dim_feedforward"], p["dropout"], p["attn_dropout"], p["norm_first"])
                for _ in range(p["num_layers"])
            )
            self.head = nn.Linear(window * d, out_dim)  # flatten head
            if zero_head:
                # The structured mode predicts a residual over a prior: starting
                # at zero, the untrained model is that prior exactly.
                nn.init.zeros_(self.head.weight)
                nn.init.zeros_(self.head.bias)
            if p["zero_init_residual"]:
                # Residual branches start as the identity, so the untrained model
                # is a linear autoregressor on the normalised window (embedding ->
                # flatten head); attention/feed-forward learn the corrections.
                for layer in self.layers:
                    for lin in (layer.proj, layer.ff2):
                        nn.init.zeros_(lin.weight)
                        nn.init.zeros_(lin.bias)

        def forward(self, x, mask=None):
            h = self.embed(x)
            if mask is not None:
                h = torch.where(mask[..., None], self.mask_token.to(h.dtype), h)
            h = h + self.pos
            for layer in self.layers:
                h = layer(h)
            return self.head(h.flatten(1))

    return MotionTransformer()


def mask_ratio(p: dict[str, Any], it: int) -> float:
    """Masked fraction of the input window at iteration `it`: a linear anneal
    from mask_ratio_start to mask_ratio_end over the first mask_anneal_frac of
    training (0 without masking)."""
    if not p["masking"]:
        return 0.0
    span = max(1.0, p["mask_anneal_frac"] * p["iterations"])
    a = min(1.0, it / span)
    return (1.0 - a) * p["mask_ratio_start"] + a * p["mask_ratio_end"]


def minibatches(n: int, batch: int, iterations: int, gen):
    """(iteration, indices) of every optimiser step: batches drawn without
    replacement from a permutation of range(n), a fresh one when it runs out."""
    import torch

    perm = torch.randperm(n, generator=gen)
    cursor = 0
    for it in range(iterations):
        if cursor + batch > n:
            perm = torch.randperm(n, generator=gen)
            cursor = 0
        yield it, perm[cursor : cursor + batch]
        cursor += batch


def optimiser_step(loss, model, opt, sched, grad_clip: float, it: int) -> None:
    """One Adam step with global grad-norm clipping; a non-finite loss stops training."""
    import torch

    if not torch.isfinite(loss):
        raise MogafError(f"forecast.mogaf: training diverged (non-finite loss at iteration {it})")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    opt.step()
    sched.step()


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
    """The paper's lightweight (LW) forecaster; `num_layers: 5` gives HC."""

    NAME = "mogaf"
    DEFAULTS = DEFAULTS
    MIN_FRAMES = 3  # L_acc needs mu_{T-1} and mu_{T-2} inside the input window

    def _check(self) -> None:
        p = self.params
        for key in ("d_model", "nhead", "dim_feedforward", "num_layers", "iterations", "batch_size", "rollout_chunk"):
            if p[key] < 1:
                raise MogafError(f"forecast.mogaf: parameter '{key}' must be >= 1, got {p[key]}")
        for key in ("batch_tokens", "weight_decay"):
            if p[key] < 0:
                raise MogafError(f"forecast.mogaf: parameter '{key}' must be >= 0, got {p[key]}")
        if p["d_model"] % p["nhead"]:
            raise MogafError(f"forecast.mogaf: d_model ({p['d_model']}) must be divisible by nhead ({p['nhead']})")
        if not (0.0 <= p["mask_ratio_end"] <= p["mask_ratio_start"] < 1.0):
            raise MogafError("forecast.mogaf: need 0 <= mask_ratio_end <= mask_ratio_start < 1")
        if not (0.0 < p["mask_anneal_frac"] <= 1.0):
            raise MogafError("forecast.mogaf: mask_anneal_frac must be in (0, 1]")
        if p["norm_eps"] <= 0:
            raise MogafError("forecast.mogaf: norm_eps must be > 0")
        if p["mode"] not in MODES:
            raise MogafError(f"forecast.mogaf: mode must be one of {', '.join(MODES)}, got {p['mode']!r}")
        structured_params(p)  # refuses bad structured settings in either mode
        if p["loss_space"] not in ("normalized", "pose"):
            raise MogafError(f"forecast.mogaf: loss_space must be 'normalized' or 'pose', got {p['loss_space']!r}")

    def mask_ratio(self, it: int) -> float:
        """Masked fraction of the input window at iteration `it` (linear anneal)."""
        return mask_ratio(self.params, it)

    def _fit(self, obs: np.ndarray) -> None:
        self._check()
        if self.params["mode"] == "structured":
            # The backtest's length depends on the forecast horizon: fitted in _rollout.
            structured_params(self.params)
            return
        self._fit_paper(obs)

    def _rollout(self, n_steps: int) -> np.ndarray:
        if self.params["mode"] == "structured":
            start = time.perf_counter()
            fitted, info = fit_structured(self._obs, self.params, self.seed, self.rigid_hint, n_steps)
            self.info.update(info)
            self.info["train_time_s"] = self.info.get("train_time_s", 0.0) + time.perf_counter() - start
            return fitted.rollout(n_steps)
        return self._rollout_paper(n_steps)

    def _fit_paper(self, obs: np.ndarray) -> None:
        import torch

        p = self.params
        g, t, _ = obs.shape
        window = t - 1
        self.window = window
        xin = obs[:, :window]
        target = obs[:, window]
        xn, mean, std = instance_norm(xin, p["norm_eps"])

        with torch_determinism(self.seed, p["num_threads"] or None):
            gen = torch.Generator().manual_seed(self.seed)
            model = _build_model(window, p)
            X = torch.from_numpy(xn).float()
            M = torch.from_numpy(mean).float()
            S = torch.from_numpy(std).float()
            Y = torch.from_numpy(target).float()
            Yn = torch.from_numpy((target - mean) / std).float()
            normalized_loss = p["loss_space"] == "normalized"
            mu1 = torch.from_numpy(obs[:, window - 1, :3]).float()
            mu2 = torch.from_numpy(obs[:, window - 2, :3]).float()
            opt = torch.optim.Adam(model.parameters(), lr=p["lr"], weight_decay=p["weight_decay"])
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=p["iterations"], eta_min=p["lr_min"])
            bs = min(batch_for_window(p["batch_size"], p["batch_tokens"], window), g)
            model.train()
            loss_val = float("nan")
            pred_val = acc_val = float("nan")
            for it, idx in minibatches(g, bs, p["iterations"], gen):
                x = X[idx]
                mask = None
                span = int(round(self.mask_ratio(it) * window))
                if span > 0:
                    starts = torch.randint(0, window - span + 1, (bs,), generator=gen)
                    steps = torch.arange(window)[None, :]
                    mask = (steps >= starts[:, None]) & (steps < starts[:, None] + span)
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
                loss = l_pred + p["lambda_acc"] * l_acc
                optimiser_step(loss, model, opt, sched, p["grad_clip"], it)
                loss_val, pred_val, acc_val = loss.item(), l_pred.item(), l_acc.item()
            model.eval()
        self.model = model
        self.info.update(
            final_loss=loss_val,
            final_loss_pred=pred_val,
            final_loss_acc=acc_val,
            iterations=p["iterations"],
            epochs=p["iterations"] * bs / g,
            batch_size=bs,
            window=window,
            num_layers=p["num_layers"],
            masking=p["masking"],
            n_params=int(sum(v.numel() for v in model.parameters())),
        )

    def predict_next(self, window: np.ndarray) -> np.ndarray:
        """One step: (G, T-1, 7) float64 poses -> (G, 7) next pose (unit quaternion)."""
        import torch

        p = self.params
        xn, mean, std = instance_norm(window, p["norm_eps"])
        out = np.empty((window.shape[0], 7))
        chunk = p["rollout_chunk"]
        with torch.no_grad():
            for s in range(0, window.shape[0], chunk):
                y = self.model(torch.from_numpy(xn[s : s + chunk]).float()).double().numpy()
                out[s : s + chunk] = y
        out = out * std + mean
        q = quat.normalize(out[:, 3:])
        out[:, 3:] = quat.align_to(q, window[:, -1, 3:])
        return out

    def _rollout_paper(self, n_steps: int) -> np.ndarray:
        p = self.params
        win = self._obs[:, -self.window :].copy()
        out = np.empty((win.shape[0], n_steps, 7))
        with torch_determinism(self.seed, p["num_threads"] or None):
            for k in range(n_steps):
                nxt = self.predict_next(win)
                out[:, k] = nxt
                win = np.concatenate([win[:, 1:], nxt[:, None]], axis=1)
        return out


class MoGaFPaperForecaster(MoGaFForecaster):
    """The paper's forecaster beside the default one: MoGaF's settings with
    `mode: paper` ("MoGaF (paper)" in tables)."""

    NAME = "mogaf_paper"
    DEFAULTS = {**DEFAULTS, "mode": "paper"}

    def __init__(self, params=None, seed: int = 0):
        super().__init__(params, seed)
        self.params["mode"] = "paper"  # whatever forecast.mogaf.mode says
