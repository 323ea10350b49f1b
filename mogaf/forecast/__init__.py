"""Group-wise motion forecasting: the MoGaF forecaster and its baselines.

Input: one group's observed trajectories, float64 (G, T, 7) on a uniform time
grid, x_t = [mu_t (3), q_t (4, wxyz unit quaternion, world orientation)].
Output: (G, n_steps, 7) poses at the next n_steps timesteps.

    result = fit_and_rollout("mogaf", observed, n_steps, params={}, seed=0)
    result.poses, result.info

Methods (each with a DEFAULTS mapping naming the source of every value):
    mogaf              MoGaF; by default structure-aware (mogaf.forecast.structured),
                       `mode: paper` gives the paper's transformer forecaster
                       exactly (LW; num_layers=5 -> HC)
    mogaf_paper        the paper's forecaster beside the default: MoGaF with
                       `mode: paper`, reading forecast.mogaf's settings
    gcn                GaussianPrediction-style GCN_xyzr on control points
    ode                ODE-GS-style transformer-encoder latent ODE
    constant_velocity  constant body-frame twist of the last two poses
    frozen             the last observed pose, repeated

Every method sign-canonicalises its input quaternions first, so q -> -q in the
observation never changes a prediction. Torch-based methods are deterministic
on CPU for a given seed (forked RNG, deterministic kernels).

A forecaster's settings are loaded and checked once (registry.load_settings,
or make_forecaster from a mapping); fit(observed, rigid, horizon) fits and
rollout(n_steps) rolls out (structured MoGaF needs the horizon at fit time).

Modules: params (METHODS, the config section of each method), registry
(load_settings, make_forecaster, defaults, fit_and_rollout), stage (the
pipeline stage; observability: the views' directions it scales the
structured forecast by), base (Forecaster), one module per forecaster (classical,
gcn, ode, transformer: the paper mode, structured: the default mode), and the
structured mode's parts: mogaf_settings (MogafRun), trajectory, group_motion,
channel_net, candidates. Import a name from the module defining it.
"""
