"""The transformer network of the MoGaF forecaster and its training-loop helpers.

_build_model (encoder layers over a window of poses, optional zero-initialised
head), the sinusoidal positions, the masking anneal (mask_ratio), minibatch
order and one clipped optimiser step. Shared by the per-Gaussian forecaster
(mogaf.forecast.transformer) and the structured mode's per-channel forecaster
(mogaf.forecast.structured); torch is imported inside the functions so that
importing this module stays cheap.
"""

from __future__ import annotations

import math
from typing import Any

from mogaf.errors import MogafError


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

        def __init__(
            self, d: int, nhead: int, dim_ff: int, dropout: float, attn_dropout: float, norm_first: bool
        ) -> None:
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
            d = p.d_model
            self.embed = nn.Linear(in_dim, d)
            # Learned [MASK] embedding replacing masked frames (BERT-style, the
            # paper's cited inspiration for masked motion modelling).
            self.mask_token = nn.Parameter(torch.randn(d) * 0.02)
            self.register_buffer("pos", _sinusoid(window, d), persistent=False)
            self.layers = nn.ModuleList(
                EncoderLayer(d, p.nhead, p.dim_feedforward, p.dropout, p.attn_dropout, p.norm_first)
                for _ in range(p.num_layers)
            )
            self.head = nn.Linear(window * d, out_dim)  # flatten head
            if zero_head:
                # The structured mode predicts a residual over a prior: starting
                # at zero, the untrained model is that prior exactly.
                nn.init.zeros_(self.head.weight)
                nn.init.zeros_(self.head.bias)
            if p.zero_init_residual:
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
    if not p.masking:
        return 0.0
    span = max(1.0, p.mask_anneal_frac * p.iterations)
    a = min(1.0, it / span)
    return (1.0 - a) * p.mask_ratio_start + a * p.mask_ratio_end


def span_masks(batch: int, length: int, span: int, maskable: int, gen, device):
    """(batch, length) bool masks, each one contiguous run of `span` positions
    starting at a random position in [0, maskable - span] (drawn from the
    CPU generator `gen`, so every device masks the same frames), on `device`."""
    import torch

    starts = torch.randint(0, maskable - span + 1, (batch,), generator=gen)
    pos = torch.arange(length)[None, :]
    return ((pos >= starts[:, None]) & (pos < starts[:, None] + span)).to(device)


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
