"""Settings of the forecast baselines: GSPred's GCN (config section
`forecast.gcn`) and ODE-GS's latent ODE (`forecast.ode`), each field with the
upstream file or option its default comes from.

Each forecaster's DEFAULTS is defaults(<its settings>); the method table is in
mogaf.forecast.params.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..settings import defaults, setting


@dataclass(frozen=True)
class GCNSettings:
    """Settings of the GCN baseline, GSPred (config section `forecast.gcn`)."""

    # graph nodes / skinning -- scripts/predict/d-nerf/*.sh
    n_nodes: int = setting(100, "max_keypoints=100 (options: --max_points 100)", minimum=1)
    nearest_num: int = setting(
        6, "nearest_num=6 network -- options/gaussian_option.py gcn_training + scripts/predict/d-nerf/*.sh", minimum=1
    )
    input_size: int = setting(10, 'input_size=10 (frames in, "window 10 -> 1")', minimum=1)
    output_size: int = setting(1, "--output_size 1", minimum=1)
    num_stage: int = setting(
        6, "num_stage=6 residual GC blocks (option default 4, every predict script sets 6)", minimum=1
    )
    linear_size: int = setting(128, "--linear_size 128 (hidden features)", minimum=1)
    dropout: float = setting(0.0, "--dropout 0.")
    no_mapping: bool = setting(
        False,
        "--no_mapping off: output through Linear-ReLU-Linear optimisation -- train_GCN.py + scripts/predict/d-nerf/*.sh",
    )
    epochs: int = setting(2001, "epoch=2001", minimum=1)
    steps: int = setting(
        0,
        "ours: 0 = `epochs` as above; N > 0 = as many epochs as give this group at least N Adam steps (ceil(N / batches per epoch)), a budget that does not grow or shrink with the group's sequence length",
        minimum=0,
    )
    batch_size: int = setting(32, "--batch_size 32 (drop_last=True)", minimum=1)
    lr: float = setting(0.01, "Adam(lr=0.01, eps=1e-15)")
    adam_eps: float = setting(1e-15, "GSPred train_GCN.py: Adam(lr=0.01, eps=1e-15)")
    lr_min: float = setting(1e-4, "CosineAnnealingLR(T_max=epoch, eta_min=1e-4)")
    noise_init: float = setting(0.0, "noise_init=0 in every predict script (option default 0.1)")
    noise_step: int = setting(100, "noise_step=100 runtime")
    num_threads: int = setting(0, "0 = leave torch's intra-op thread count alone")


GCN_DEFAULTS: dict[str, Any] = defaults(GCNSettings)


@dataclass(frozen=True)
class ODESettings:
    """Settings of the latent-ODE baseline, ODE-GS (config section `forecast.ode`)."""

    # model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)
    latent_dim: int = setting(
        64, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    d_model: int = setting(
        128, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    nhead: int = setting(
        8, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    num_encoder_layers: int = setting(
        4, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    num_decoder_layers: int = setting(
        4, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    ode_nhidden: int = setting(
        64, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    decoder_nhidden: int = setting(
        128, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    ode_layers: int = setting(
        4, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=2
    )
    use_tanh: bool = setting(
        True, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)"
    )
    encoder_dropout: float = setting(
        0.1, "extrapolation_ode_model.py: TransformerEncoderLayer(dropout=0.1, dim_feedforward=4*d_model)"
    )
    rtol: float = setting(
        1e-3, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)"
    )
    atol: float = setting(
        1e-4, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)"
    )
    max_num_steps: int = setting(
        1000,
        "ours: dopri5 step cap per output interval (torchdiffeq option); hitting it is flagged data -- config_DNerf_default.yaml `data:`",
        minimum=1,
    )
    time_split: float = setting(0.8, "observed part of the normalised [0, 1] sequence time", exclusive_minimum=0)
    obs_time_span: float = setting(
        0.6,
        "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)",
        exclusive_minimum=0,
    )
    max_extrap_time_span: float = setting(
        0.2,
        "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)",
        exclusive_minimum=0,
    )
    extrap_points: int = setting(
        10, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    num_time_windows: int = setting(
        50, "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)", minimum=1
    )
    max_gaussians_per_epoch: int = setting(
        50000,
        "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)",
        minimum=1,
    )
    batch_size: int = setting(
        1024,
        "model -- configs/config_DNerf_default.yaml `model:` (D-NeRF, the MoGaF paper's comparison set)",
        minimum=1,
    )
    # train -- config_DNerf_default.yaml `train:` / `scheduler:`
    epochs: int = setting(40, "train -- config_DNerf_default.yaml `train:` / `scheduler:`", minimum=0)
    steps: int = setting(
        0,
        "ours: 0 = `epochs` as above; N > 0 = as many epochs as give this group at least N Adam steps (ceil(N / batches per epoch)), a budget that does not grow or shrink with the group's size",
        minimum=0,
    )
    lr: float = setting(1e-3, "Adam (train_extrapolation.py passes no weight decay)")
    lr_min: float = setting(1e-5, "CosineAnnealingLR eta_min, T_max = 40 = epochs")
    reg_weight: float = setting(1e-5, "latent second-derivative regulariser")
    xyz_reg_weight: float = setting(1e-3, "xyz acceleration regulariser")
    reg_temperature: float = setting(0.05, "train -- config_DNerf_default.yaml `train:` / `scheduler:`")
    expected_traj_loss_init: float = setting(0.05, "train -- config_DNerf_default.yaml `train:` / `scheduler:`")
    expected_traj_loss_end: float = setting(0.0, "train -- config_DNerf_default.yaml `train:` / `scheduler:`")
    reg_use_ema: bool = setting(True, "train -- config_DNerf_default.yaml `train:` / `scheduler:`")
    reg_ema_decay: float = setting(0.9, "train -- config_DNerf_default.yaml `train:` / `scheduler:`")
    # runtime
    num_threads: int = setting(0, "0 = leave torch's intra-op thread count alone")
    rollout_chunk: int = setting(4096, "Gaussians per solve at inference", minimum=1)


ODE_DEFAULTS: dict[str, Any] = defaults(ODESettings)
