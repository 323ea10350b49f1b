"""ODE-GS-style latent neural ODE baseline ("ODE-GS-SoM" in the MoGaF paper).

Upstream (preacherwhite/ODE-GS, scene/extrapolation_ode_model.py:
TransformerLatentODEWrapper; train_extrapolation.py; utils/ode_dataset_utils.py:
DynamicLengthDataset; configs/config_DNerf_default.yaml): a transformer
encoder reads a Gaussian's observed window; its last token is projected to a
latent z0; a latent ODE with an MLP vector field is integrated with an
adaptive dopri5 solver from the last observed time to the query times; an MLP
decoder maps latent states to Gaussian states. Deterministic (no VAE) with an
L1 trajectory loss, a latent second-derivative regulariser and an xyz
acceleration regulariser, both scaled per iteration by an EMA-driven factor.

Our adaptation to discrete per-group trajectories:
  * State x = [mu, q] (7; upstream also carries 3 scale channels).
  * Time: the observed frames span [0, time_split] (upstream's normalised
    time with the observed part ending at time_split = 0.8), so the frame step
    is dt = time_split / (T - 1).
  * Upstream samples its deformation field at 30 / 10 continuous times inside
    windows of 0.6 / up to 0.2 time units. We use the observed frames inside
    windows of the same time spans: obs window = round(0.6 / dt) + 1 frames,
    targets = the next min(10, round(0.2 / dt)) frames (fewer at the end of
    the observation, as upstream's windows shrink there), at most 50 window
    starts. Inference encodes the last obs window and integrates once to all
    requested future times (no autoregression).
  * Solver: torchdiffeq dopri5 (upstream: torchode Dopri5 + IntegralController)
    with rtol/atol from the config and a step cap. Hitting the cap (or a
    non-finite state / step-size underflow) is never fatal: a training batch is
    skipped, a rollout chunk falls back to the constant-twist extrapolation,
    and info["ode_step_cap_hit"] is set.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mogaf.errors import MogafError
from mogaf.forecast import quat
from mogaf.forecast.base import Forecaster, epochs_for, torch_determinism
from mogaf.forecast.baseline_params import ODE_DEFAULTS
from mogaf.forecast.classical import constant_twist_rollout
from mogaf.progress import Progress


class _StepCapHit(Exception):
    """The adaptive solver needed more steps than allowed (or broke down)."""


def _sinusoid(length: int, dim: int):
    import torch

    pos = torch.arange(length, dtype=torch.float64)[:, None]
    j = torch.arange(dim, dtype=torch.float64)[None, :]
    angle = pos / torch.pow(
        torch.tensor(10000.0, dtype=torch.float64), 2 * torch.div(j, 2, rounding_mode="floor") / dim
    )
    half = (dim + 1) // 2
    pe = torch.zeros(length, dim, dtype=torch.float64)
    pe[:, :half] = torch.sin(angle[:, 0::2])
    pe[:, half:] = torch.cos(angle[:, 1::2])
    return pe.float()


def _build_model(p: dict[str, Any], obs_len: int):
    from torch import nn

    act = nn.Tanh if p.use_tanh else nn.ReLU

    def init_linear(lin: nn.Linear, gain: float = 1.0) -> None:
        if p.use_tanh:
            nn.init.xavier_uniform_(lin.weight, gain=gain)
        else:
            nn.init.kaiming_uniform_(lin.weight, nonlinearity="relu")
        nn.init.zeros_(lin.bias)

    class VectorField(nn.Module):
        """Autonomous MLP dz/dt = f(z) with `ode_layers` linear layers."""

        def __init__(self) -> None:
            super().__init__()
            n, h = p.latent_dim, p.ode_nhidden
            dims = [n] + [h] * (p.ode_layers - 1) + [n]
            self.lins = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
            for lin in self.lins:
                init_linear(lin)
            self.act = act()
            self.nfe = 0
            self.nfe_cap: int | None = None

        def forward(self, t, z):
            self.nfe += 1
            if self.nfe_cap is not None and self.nfe > self.nfe_cap:
                raise _StepCapHit("function-evaluation guard")
            for lin in self.lins[:-1]:
                z = self.act(lin(z))
            return self.lins[-1](z)

    class LatentODE(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            d = p.d_model
            self.value_embedding = nn.Linear(7, d)
            nn.init.xavier_uniform_(self.value_embedding.weight)
            nn.init.zeros_(self.value_embedding.bias)
            self.register_buffer("pos", _sinusoid(obs_len, d), persistent=False)
            layer = nn.TransformerEncoderLayer(
                d_model=d, nhead=p.nhead, dim_feedforward=4 * d, dropout=p.encoder_dropout, batch_first=True
            )
            self.encoder = nn.TransformerEncoder(layer, num_layers=p.num_encoder_layers, enable_nested_tensor=False)
            self.to_z0 = nn.Linear(d, p.latent_dim)
            init_linear(self.to_z0)
            self.func = VectorField()
            h = p.decoder_nhidden
            layers: list[nn.Module] = [nn.Linear(p.latent_dim, h), act()]
            for _ in range(p.num_decoder_layers - 1):
                layers += [nn.Linear(h, h), act()]
            layers.append(nn.Linear(h, 7))
            self.decoder = nn.Sequential(*layers)
            for m in self.decoder[:-1]:
                if isinstance(m, nn.Linear):
                    init_linear(m)
            nn.init.xavier_uniform_(self.decoder[-1].weight, gain=0.01)  # small last layer, as upstream
            nn.init.zeros_(self.decoder[-1].bias)

        def encode(self, obs):
            """z0 from the last token of the encoder's output. Only that token
            is read, so the last layer runs its attention query, feed-forward
            and norms for it alone (keys and values still see every token):
            the same function as the full stack, at about three quarters of its
            cost with four layers."""
            h = self.value_embedding(obs) + self.pos
            *first, last = self.encoder.layers
            for layer in first:
                h = layer(h)
            return self.to_z0(_last_token_layer(last, h))

    return LatentODE()


def _last_token_layer(layer, h):
    """A post-norm nn.TransformerEncoderLayer's output at the last position
    only, (B, L, d) -> (B, d); dropout as the layer's own forward applies it."""
    x = h[:, -1:]
    a = layer.self_attn(x, h, h, need_weights=False)[0]
    x = layer.norm1(x + layer.dropout1(a))
    f = layer.linear2(layer.dropout(layer.activation(layer.linear1(x))))
    return layer.norm2(x + layer.dropout2(f))[:, 0]


def _solve(model, z0, times, p: dict[str, Any]):
    """dopri5 from times[0]; returns (len(times), B, latent). Raises _StepCapHit."""
    import torch
    from torchdiffeq import odeint

    cap = int(p.max_num_steps)
    func = model.func
    func.nfe = 0
    # Independent guard on function evaluations (dopri5: 6 per attempted step,
    # plus start-up), so the cap holds even with assertions disabled (python -O).
    func.nfe_cap = 7 * cap * max(len(times) - 1, 1) + 16
    try:
        z = odeint(func, z0, times, method="dopri5", rtol=p.rtol, atol=p.atol, options={"max_num_steps": cap})
    except AssertionError as exc:  # torchdiffeq: max_num_steps exceeded / underflow in dt / non-finite y
        raise _StepCapHit(str(exc)) from None
    finally:
        func.nfe_cap = None
    if not torch.isfinite(z).all():
        raise _StepCapHit("non-finite latent state")
    return z


class LatentODEForecaster(Forecaster):
    NAME = "ode"
    DEFAULTS = ODE_DEFAULTS  # forecast.baseline_params.ODESettings
    MIN_FRAMES = 4

    def _layout(self, t: int) -> tuple[float, int, int]:
        p = self.settings
        if not (p.time_split > 0 and p.obs_time_span > 0 and p.max_extrap_time_span > 0):
            raise MogafError("forecast.ode: time_split, obs_time_span and max_extrap_time_span must be > 0")
        dt = p.time_split / (t - 1)
        obs_len = int(round(p.obs_time_span / dt)) + 1
        obs_len = max(2, min(obs_len, t - 1))  # leave at least one target frame
        extrap = max(1, min(p.extrap_points, int(round(p.max_extrap_time_span / dt))))
        return dt, obs_len, extrap

    def _fit(self, obs: np.ndarray) -> None:
        import torch

        from mogaf.optim import Adam

        p = self.settings
        # each setting's own bounds are checked by its settings class (mogaf.forecast.baseline_params)
        if p.d_model % p.nhead:
            raise MogafError(f"forecast.ode: d_model ({p.d_model}) must be divisible by nhead ({p.nhead})")
        g, t, _ = obs.shape
        dt, obs_len, extrap = self._layout(t)
        self.dt, self.obs_len = dt, obs_len
        starts_all = np.arange(0, t - obs_len)  # at least one target frame after each window
        if len(starts_all) > p.num_time_windows:
            starts_all = np.unique(np.round(np.linspace(0, t - obs_len - 1, p.num_time_windows)).astype(int))
        n_win = len(starts_all)
        # Per window: observation frames [s, s+obs_len), targets up to `extrap` frames after.
        obs_idx = starts_all[:, None] + np.arange(obs_len)[None]
        tgt_idx = starts_all[:, None] + obs_len + np.arange(extrap)[None]
        tgt_mask = tgt_idx <= t - 1
        tgt_idx = np.minimum(tgt_idx, t - 1)

        cap_hits = 0
        steps_done = 0
        loss_val = float("nan")
        dev = self.device
        with torch_determinism(self.seed, p.num_threads or None, dev):
            # the sampling generator stays on the CPU: the same draws on every device
            gen = torch.Generator().manual_seed(self.seed)
            model = _build_model(p, obs_len).to(dev)  # built on the CPU: the same initial weights on every device
            OBS = torch.from_numpy(obs).float().to(dev)  # (G, T, 7)
            OI = torch.from_numpy(obs_idx).to(dev)
            TI = torch.from_numpy(tgt_idx).to(dev)
            TM = torch.from_numpy(tgt_mask).to(dev)
            times = (torch.arange(extrap + 1, dtype=torch.float32) * dt).to(dev)  # last obs frame, then targets
            opt = Adam(model.parameters(), lr=p.lr)
            per_epoch = math.ceil(n_win * min(g, p.max_gaussians_per_epoch) / p.batch_size)
            epochs = epochs_for(p.epochs, p.steps, per_epoch)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(epochs, 1), eta_min=p.lr_min)
            reg_w, xyz_w = p.reg_weight, p.xyz_reg_weight
            ema = None
            model.train()
            bar = Progress("forecast.ode batch", epochs * per_epoch)
            for _epoch in range(epochs):
                gsel = torch.randperm(g, generator=gen)[: min(g, p.max_gaussians_per_epoch)]
                pairs = torch.cartesian_prod(torch.arange(n_win), gsel)  # (window, Gaussian) samples
                pairs = pairs[torch.randperm(len(pairs), generator=gen)]
                tot, nb = 0.0, 0
                for s in range(0, len(pairs), p.batch_size):
                    bar.update(**({} if ema is None else {"loss": ema}))
                    wi, gi = pairs[s : s + p.batch_size].to(dev).unbind(1)
                    x_obs = OBS[gi[:, None], OI[wi]]  # (B, L, 7)
                    x_tgt = torch.cat([x_obs[:, -1:], OBS[gi[:, None], TI[wi]]], 1)  # (B, E+1, 7)
                    m = torch.cat([torch.ones(len(wi), 1, dtype=torch.bool, device=dev), TM[wi]], 1)  # (B, E+1)
                    try:
                        z0 = model.encode(x_obs)
                        z = _solve(model, z0, times, p).transpose(0, 1)  # (B, E+1, latent)
                    except _StepCapHit:
                        cap_hits += 1
                        continue
                    pred = model.decoder(z)
                    mf = m[..., None].float()
                    l_pred = ((pred - x_tgt).abs() * mf).sum() / (mf.sum() * 7)
                    loss = l_pred
                    if reg_w > 0:
                        loss = loss + reg_w * self._latent_reg(model, z, times)
                    if xyz_w > 0 and z.shape[1] >= 3:
                        vel = torch.diff(pred[..., :3], dim=1) / torch.diff(times).clamp_min(1e-6)[None, :, None]
                        acc = torch.diff(vel, dim=1)
                        am = (m[:, 2:])[..., None].float()
                        loss = loss + xyz_w * ((acc**2) * am).sum() / (am.sum() * 3).clamp_min(1)
                    if not torch.isfinite(loss):
                        cap_hits += 1
                        continue
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
                    steps_done += 1
                    tot += loss.item()
                    nb += 1
                    # Adaptive regulariser scale (train_extrapolation.py), from the EMA of the L1 loss.
                    lv = l_pred.item()
                    ema = (
                        lv if (ema is None or not p.reg_use_ema) else p.reg_ema_decay * ema + (1 - p.reg_ema_decay) * lv
                    )
                    scale = self._reg_scale(ema)
                    reg_w, xyz_w = p.reg_weight * scale, p.xyz_reg_weight * scale
                if nb:
                    sched.step()
                    loss_val = tot / nb
            bar.close()
            model.eval()
        self.model = model
        self.info.update(
            final_loss=loss_val,
            epochs=epochs,
            iterations=steps_done,
            obs_window=obs_len,
            extrap_frames=extrap,
            train_windows=n_win,
            dt=dt,
            ode_cap_hits_train=cap_hits,
            ode_step_cap_hit=cap_hits > 0,
        )

    @staticmethod
    def _latent_reg(model, z, times):
        """Mean squared second derivative of the latent path, from the vector
        field at the (detached) solution points, in window-normalised time."""
        import torch

        b, n, d = z.shape
        if n < 2:
            return z.new_zeros(())
        f = model.func
        cap, f.nfe_cap = f.nfe_cap, None
        der = f(None, z.detach().reshape(-1, d)).reshape(b, n, d)
        f.nfe_cap = cap
        tn = (times - times[0]) / (times[-1] - times[0]).clamp_min(1e-6)
        dtn = torch.diff(tn).clamp_min(1.0 / max(n - 1, 1))
        sec = torch.diff(der, dim=1) / dtn[None, :, None]
        return (sec**2).mean()

    def _reg_scale(self, loss_value: float) -> float:
        p = self.settings
        init, end = p.expected_traj_loss_init, p.expected_traj_loss_end
        if init < end:
            init, end = end, init
        r = min(max((loss_value - end) / max(init - end, 1e-8), 0.0), 1.0)
        return float(min(max(math.exp(-r / max(p.reg_temperature, 1e-8)), 0.0), 1.0))

    def _rollout(self, n_steps: int) -> np.ndarray:
        import torch

        p = self.settings
        obs = self._obs
        g = obs.shape[0]
        out = np.empty((g, n_steps, 7))
        dev = self.device
        times = (torch.arange(n_steps + 1, dtype=torch.float32) * self.dt).to(dev)
        chunks_failed = 0
        with torch_determinism(self.seed, p.num_threads or None, dev), torch.no_grad():
            for s in range(0, g, p.rollout_chunk):
                x = torch.from_numpy(obs[s : s + p.rollout_chunk, -self.obs_len :]).float().to(dev)
                try:
                    z = _solve(self.model, self.model.encode(x), times, p)  # (n+1, B, latent)
                    pred = self.model.decoder(z[1:]).transpose(0, 1).cpu().double().numpy()
                    if not np.isfinite(pred).all():
                        raise _StepCapHit("non-finite decoded state")
                    q = quat.normalize(pred[..., 3:])
                    if (np.linalg.norm(pred[..., 3:], axis=-1) < 1e-8).any():
                        raise _StepCapHit("degenerate decoded quaternion")
                    pred[..., 3:] = q
                    out[s : s + len(x)] = pred
                except _StepCapHit:
                    chunks_failed += 1
                    out[s : s + len(x)] = constant_twist_rollout(
                        obs[s : s + len(x), -2], obs[s : s + len(x), -1], n_steps
                    )
        if chunks_failed:
            self.info["ode_step_cap_hit"] = True
            self.info["rollout_fallback"] = "constant_velocity"
        self.info["ode_cap_hits_rollout"] = chunks_failed
        return out
