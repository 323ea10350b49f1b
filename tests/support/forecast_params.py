"""Small forecaster budgets: the tests check behaviour, not converged accuracy."""

from __future__ import annotations

FAST = {
    "mogaf": {"iterations": 40, "batch_size": 32},
    "mogaf_paper": {"iterations": 40, "batch_size": 32},
    "gcn": {"n_nodes": 12, "num_stage": 1, "linear_size": 16, "epochs": 10, "num_threads": 1},
    "ode": {
        "latent_dim": 8,
        "d_model": 16,
        "nhead": 2,
        "num_encoder_layers": 1,
        "num_decoder_layers": 2,
        "ode_nhidden": 16,
        "decoder_nhidden": 16,
        "epochs": 1,
        "batch_size": 128,
        "max_gaussians_per_epoch": 32,
        "num_threads": 1,
    },
    "constant_velocity": {},
    "frozen": {},
}
