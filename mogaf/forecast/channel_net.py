"""The learned candidate of the structured MoGaF forecaster: one shared
network over independent scalar series (channel-independent, PatchTST /
RevIN style), predicting `horizon` steps at once as a residual over each
series' constant velocity."""

from __future__ import annotations

from typing import Any

import numpy as np

from mogaf.devices import resolve_device
from mogaf.errors import MogafError
from mogaf.forecast.base import torch_determinism
from mogaf.forecast.mogaf_settings import MogafRun
from mogaf.forecast.transformer_net import _build_model, mask_ratio, minibatches, optimiser_step, span_masks
from mogaf.progress import Progress


def window_sizes(length: int, context: int, horizon: int) -> tuple[int, int] | None:
    """(context, horizon) that leave at least one training window in `length`
    values, or None when the series is too short for the learned forecaster."""
    h = max(1, min(horizon, (length - 1) // 3))
    c = min(context, length - h)
    return (c, h) if c >= 2 else None


class ChannelForecaster:
    """One shared network over independent scalar series (S, T): context ->
    next `horizon` values, a residual over each series' constant velocity."""

    def __init__(self, run: MogafRun, seed: int, device: Any = "cpu") -> None:
        self.run = run
        self.seed = int(seed)
        # the torch device the network trains and runs on (a name is resolved: "auto" too)
        self.device = resolve_device(device, "forecast.mogaf") if isinstance(device, str) else device

    @staticmethod
    def normalise(ctx: np.ndarray, floor: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Anchor at the last value, divide by the spread (floored: a still
        channel is not blown up to unit scale)."""
        anchor = ctx[:, -1:]
        scale = np.sqrt(ctx.var(axis=1, keepdims=True) + floor[:, None] ** 2)
        return (ctx - anchor) / scale, anchor, scale

    def fit(self, series: np.ndarray, floor: np.ndarray) -> ChannelForecaster:
        import torch

        from mogaf.optim import Adam

        net, own = self.run.net, self.run.own
        S, T = series.shape
        sizes = window_sizes(T, int(own.context), int(own.horizon))
        if sizes is None:
            raise MogafError(f"forecast.mogaf: {T} observed frames are too few for the learned forecaster")
        self.context, self.horizon = L, H = sizes
        n_win = T - L - H + 1
        rng = np.random.default_rng([self.seed, 7])
        total = S * n_win
        # (channel, window) pairs drawn by flat index: a big group never builds all of them
        flat = (
            np.sort(rng.choice(total, int(own.max_train_windows), replace=False))
            if total > own.max_train_windows
            else np.arange(total)
        )
        pairs = np.stack(np.divmod(flat, n_win), axis=-1)
        idx = pairs[:, 1:2] + np.arange(L + H)[None, :]
        win = series[pairs[:, :1], idx]
        xn, anchor, scale = self.normalise(win[:, :L], floor[pairs[:, 0]])
        yn = (win[:, L:] - anchor) / scale
        steps_ahead = np.arange(1, H + 1, dtype=np.float64)

        dev = self.device
        with torch_determinism(self.seed, net.num_threads or None, dev):
            # the sampling generator stays on the CPU: the same draws on every device
            gen = torch.Generator().manual_seed(self.seed)
            # built on the CPU: the same initial weights on every device
            model = _build_model(L, net, in_dim=1, out_dim=H, zero_head=True).to(dev)
            X = torch.from_numpy(xn).float()[..., None].to(dev)
            Y = torch.from_numpy(yn).float().to(dev)
            K = torch.from_numpy(steps_ahead).float().to(dev)
            n = X.shape[0]
            opt = Adam(model.parameters(), lr=net.lr, weight_decay=own.weight_decay)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=net.iterations, eta_min=net.lr_min)
            bs = min(int(net.batch_size), n)
            model.train()
            loss_val = float("nan")
            bar = Progress("forecast.mogaf fit", net.iterations)
            for it, b in minibatches(n, bs, net.iterations, gen):
                b = b.to(dev)
                x = X[b]
                mask = None
                span = int(round(mask_ratio(net, it) * (L - 2)))  # the last two values carry the prior
                if span > 0:
                    mask = span_masks(bs, L, span, L - 2, gen, dev)
                velocity = x[:, -1, 0] - x[:, -2, 0]
                pred = K[None, :] * velocity[:, None] + model(x, mask)
                l_pred = ((pred - Y[b]) ** 2).mean()
                seq = torch.cat([x[:, -2:, 0], pred], dim=1)
                l_acc = ((seq[:, 2:] - 2.0 * seq[:, 1:-1] + seq[:, :-2]) ** 2).mean()
                loss = l_pred + net.lambda_acc * l_acc
                optimiser_step(loss, model, opt, sched, net.grad_clip, it)
                loss_val = loss.item()
                bar.update(it + 1, loss=loss_val)
            bar.close()
            model.eval()
        self.model = model
        self.final_loss = loss_val
        self.num_windows = n
        return self

    def rollout(self, series: np.ndarray, floor: np.ndarray, n_steps: int) -> np.ndarray:
        """(S, n_steps) values after the end of `series` (S, >= context)."""
        import torch

        L, H = self.context, self.horizon
        hist = np.array(series[:, -L:], dtype=np.float64)
        out = np.empty((hist.shape[0], n_steps))
        chunk = int(self.run.net.rollout_chunk)
        steps_ahead = np.arange(1, H + 1, dtype=np.float64)
        done = 0
        with torch_determinism(self.seed, self.run.net.num_threads or None, self.device), torch.no_grad():
            while done < n_steps:
                xn, anchor, scale = self.normalise(hist[:, -L:], floor)
                res = np.empty((hist.shape[0], H))
                for s in range(0, hist.shape[0], chunk):
                    x = torch.from_numpy(xn[s : s + chunk]).float()[..., None].to(self.device)
                    res[s : s + chunk] = self.model(x).cpu().double().numpy()
                pred = steps_ahead[None, :] * (xn[:, -1:] - xn[:, -2:-1]) + res
                values = pred * scale + anchor
                take = min(H, n_steps - done)
                out[:, done : done + take] = values[:, :take]
                hist = np.concatenate([hist, values[:, :take]], axis=1)[:, -L:]
                done += take
        return out


class NetworkMean:
    """Fitted ChannelForecasters as one: rollout() is the mean of their
    rollouts (each reads its own context and predicts its own horizon)."""

    def __init__(self, models: tuple[ChannelForecaster, ...]) -> None:
        if not models:
            raise MogafError("forecast.mogaf: a mean of no networks")
        self.models = models

    def rollout(self, series: np.ndarray, floor: np.ndarray, n_steps: int) -> np.ndarray:
        return np.mean([m.rollout(series, floor, n_steps) for m in self.models], axis=0)
