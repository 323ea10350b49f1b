"""Forecast settings: one dataclass per method's config section
(forecast.mogaf with its nested `structured` here; forecast.gcn and
forecast.ode in mogaf.forecast.baseline_params), the method names and which
section each method reads.

Each forecaster's DEFAULTS is defaults(<its settings>).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from ..errors import MogafError
from ..settings import as_dict, defaults, load, section_schema, setting
from .baseline_params import GCNSettings, ODESettings

# The structured mode's candidates, simplest first: a tie goes to the simpler.
STRUCTURED_CANDIDATES = (
    "frozen",
    "constant_velocity",
    "linear_trend",
    "damped_trend",
    "braking",
    "constant_acceleration",
    "learned",
)


@dataclass(frozen=True)
class StructuredSettings:
    """Settings of the structured MoGaF forecaster (config section `forecast.mogaf.structured`)."""

    context: int = setting(
        16, "past values the network reads per channel (shorter when fewer frames are observed)", minimum=2
    )
    horizon: int = setting(8, "values predicted per forward pass (multi-step head and loss)", minimum=1)
    weight_decay: float = setting(
        0.0,
        "replaces the paper mode's 0.03; none, because decay shrinks the residual over the per-channel constant "
        "velocity, so a thrown sphere's fall would not be learned",
        minimum=0,
    )
    rigid_residual: float = setting(
        0.05, "rigid-fit RMS residual / group RMS radius under which a group without a hint is rigid", minimum=0
    )
    still_factor: float = setting(
        3.0, "non-rigid groups: a Gaussian moving less than this x the noise level stays still", minimum=0
    )
    nonrigid_motion: Literal["per_gaussian", "rigid_body", "rigid_parts"] = setting(
        "rigid_parts",
        "how a group that is not rigid is forecast: 'per_gaussian' (each moving Gaussian's own series), "
        "'rigid_body' (the group's rigid-fit motion, centroid and rotation, carried to its moving members, whose "
        "shape stays as last observed) or 'rigid_parts' (the group cut into at most `rigid_parts` parts that each "
        "move as one rigid body, each forecast as a rigid group is). Each Gaussian's extrapolated series carries its "
        "own noise, which tears a surface apart over the forecast (docs/forecasting.md, variants "
        "nonrigid_rigid_body, nonrigid_per_gaussian)",
    )
    rigid_parts: int = setting(
        8,
        "nonrigid_motion: rigid_parts: the most parts a group is cut into (K-motions on the observed trajectories; "
        "fewer where parts would have under 3 members or move alike)",
        minimum=1,
    )
    parts_unexplained: float = setting(
        0.45,
        "nonrigid_motion: rigid_parts: a group whose parts leave more than this share of its motion unexplained "
        "(RMS distance from each part's rigid fit over RMS displacement) is forecast per Gaussian instead: about 0.5 "
        "where members each keep their own velocity, lower on reconstructed objects (docs/forecasting.md)",
        minimum=0,
    )
    gate: bool = setting(True, "backtest the candidates per group (false: the learned forecaster alone)")
    backtest_frac: float = setting(
        0.5,
        "the backtest holds back this share of the observed frames, at most the forecast horizon",
        exclusive_minimum=0,
        exclusive_maximum=1,
    )
    backtest_origins: int = setting(
        1,
        "combine: weighted (select scores one window): origins the backtest scores from, 1 = the last h observed "
        "frames held back (backtest_frac); n > 1 adds origins holding back about h/2, h/4 and so on (at least 2), the "
        "learned candidate being the backtest's network at each (no extra fit), and weighs each candidate by its "
        "mean weight over the origins. Later origins see a change of motion in the last frames (an object that "
        "stopped)",
        minimum=1,
    )
    backtest_margin: float = setting(
        0.0,
        "combine: select: the learned forecaster is chosen only when its backtest error is this share below the best "
        "other candidate's (0 = the lowest score wins, the learned forecaster treated like the others)",
        minimum=0,
        exclusive_maximum=1,
    )
    combine: Literal["select", "weighted"] = setting(
        "weighted",
        "how the backtest decides: 'weighted' (every candidate's forecast, weighted by its inverse squared backtest "
        "error; a rigid group blends as one pose, so it stays rigid) or 'select' (the lowest score wins). Weighted by "
        "default: one backtest window is a noisy judge, and a choice won by a few percent often does not hold in the "
        "future (docs/forecasting.md)",
    )
    max_train_windows: int = setting(
        65536, "training windows kept per fit (random, seeded): bounds memory for big groups", minimum=1
    )
    candidates: list = setting(
        ["frozen", "linear_trend", "learned"],
        "what the backtest weighs (or selects among): any of frozen, constant_velocity (the last step's velocity; "
        "a rigid group's last twist), linear_trend (each series' least-squares line through its last `trend_window` "
        "values), damped_trend (that line, its speed halving every `trend_half_life` steps), braking (each vector's "
        "velocity from its least-squares parabola through the last `context` values, slowing to a stop where "
        "that parabola decelerates), constant_acceleration (each series' least-squares parabola through its last "
        "`context` values) and learned, at least one. The "
        "default takes linear_trend over constant_velocity, as a reconstruction's last step is its least "
        "constrained, and leaves out constant_acceleration, whose parabola contacts bend off within the forecast "
        "(docs/forecasting.md)",
        schema={
            "items": {"enum": list(STRUCTURED_CANDIDATES)},
            "minItems": 1,
            "uniqueItems": True,
        },
    )
    trend_window: int = setting(
        8,
        "values the linear_trend and damped_trend candidates fit their line through (2 = each series' last step; "
        "a rigid group's series are its centroid and rotation, so that line is not its twist: constant_velocity "
        "continues that). Enough that the reconstruction's least accurate last frames move the line little, few enough to "
        "follow recent changes of motion (docs/forecasting.md)",
        minimum=2,
    )
    trend_half_life: float = setting(
        8.0,
        "forecast steps over which the damped_trend candidate's speed halves (Gardner and McKenzie's damped trend). "
        "As many as the line is fitted through (trend_window): the trend is trusted about as far ahead as it was "
        "fitted, and within a backtest window, so the backtest can tell a motion that goes on from one that slows "
        "(docs/forecasting.md, variant damped_candidate)",
        exclusive_minimum=0,
    )
    backtest_neighbors: int = setting(
        32,
        "combine: weighted, non-rigid groups forecast per Gaussian (rigid groups, rigid parts and combine: select "
        "decide per group or part): each moving "
        "Gaussian is weighted by the candidates' backtest errors (and the learned one's drift) averaged over its "
        "this many nearest moving Gaussians of the group at the last observed frame, itself included; 0 (or as "
        "many as move) = one weighting per group. Per Gaussian because a non-rigid group can join parts that move "
        "differently (a swaying cloth and a thrown ball beside it); 32 is a plausible neighbourhood, not tuned",
        minimum=0,
    )
    coherent_neighbors: int = setting(
        0,
        "non-rigid groups forecast per Gaussian: each moving Gaussian's forecast motion (displacement and turn since "
        "its last observed "
        "pose) is the local affine fit over its this many nearest moving Gaussians at the last observed frame, "
        "itself included; 0 = each its own. Each Gaussian's series is extrapolated on its own, and their noise, "
        "which grows over the forecast, tears a surface apart where the truth moves it as a piece; an affine fit "
        "keeps a shift, a small turn and a stretch (docs/forecasting.md, variant coherent_forecast)",
        minimum=0,
    )
    damping: float = setting(
        0.0,
        "the forecast's speed halves every damping x T frames (T observed; Gardner and McKenzie's damped trend, "
        "applied to whatever the candidates forecast, backtest included); 0 = undamped. Trust in any extrapolation "
        "falls with its length against what was observed (docs/forecasting.md, variant damped_forecast)",
        minimum=0,
    )
    unobserved_motion: Literal["suppress", "keep"] = setting(
        "suppress",
        "motion along directions the views of the last `view_window` observed steps did not see across (along the "
        "rays of one camera filming from one side, where a reconstruction's velocity rests on depth cues alone): "
        "'suppress' scales each forecast displacement down along them, 'keep' forecasts it as the candidates do. "
        "Views spread around the scene, as the MuJoCo grid's, change nothing (mogaf.forecast.observability; "
        "docs/forecasting.md, variant "
        "keep_unobserved_motion)",
    )
    view_window: int = setting(
        8, "unobserved_motion: suppress: the last observed steps whose views count (as trend_window's line)", minimum=1
    )
    observed_spread_deg: float = setting(
        30.0,
        "unobserved_motion: suppress: a direction whose mean squared sine with the views' rays reaches sin^2 of this "
        "angle keeps its forecast motion; below, its displacement is scaled by that mean over sin^2 of it",
        exclusive_minimum=0,
        maximum=90,
    )
    track_agreement: Literal["shrink", "keep"] = setting(
        "shrink",
        "how far each rigid body's image motion over the last `track_steps` observed steps agrees with the 2D "
        "tracks on it: 'shrink' scales its forecast motion from its last observed pose by m^2 / (m^2 + e^2), m the "
        "tracks' own motion and e the model's error against them, in pixels (the least-squares scale of a velocity "
        "known to that error); 'keep' forecasts it as the candidates do. Without tracks (the multi-view layouts, as "
        "the MuJoCo grid's) nothing changes (mogaf.forecast.track_agreement; docs/forecasting.md, variant "
        "keep_track_disagreement)",
    )
    track_steps: int = setting(
        3, "track_agreement: shrink: the observed steps the motion is compared over, back from the last", minimum=1
    )
    min_tracks: int = setting(
        5,
        "track_agreement: shrink: tracks a body needs for its own scale; with fewer it takes its group's (every "
        "track on the group's members), and a group with fewer keeps its forecast",
        minimum=1,
    )
    refit_networks: int = setting(
        1,
        "networks the learned candidate fits on every observed frame (each from its own seed), whose rollouts it "
        "averages: a fit's training noise moves its forecast, and a mean of independent fits partly cancels it, "
        "at one more fit each (docs/forecasting.md, variant two_refits)",
        minimum=1,
    )
    drift_check: bool = setting(
        True,
        "the learned candidate's backtest error is combined (root sum of squares) with its refit drift: the mean "
        "distance, over the backtest's length, between the forecasts of the network refitted on every observed "
        "frame and of the backtested network. The backtest judges a network fitted on the first T - h frames; "
        "the refit also learns the last h, where a reconstruction is least accurate, and can run off there",
    )


STRUCTURED_DEFAULTS: dict[str, Any] = defaults(StructuredSettings)


@dataclass(frozen=True)
class MogafSettings:
    """Settings of the MoGaF forecaster, both modes (config section `forecast.mogaf`)."""

    mode: Literal["structured", "paper"] = setting(
        "structured",
        "ours: 'structured' (mogaf.forecast.structured, the default) or 'paper' (the paper's forecaster "
        "exactly, mogaf.forecast.transformer; config/paper.yaml, 'MoGaF (paper)' in tables)",
    )
    structured: dict = setting(
        defaults(StructuredSettings),
        "the structured mode's own settings (the paper mode ignores them)",
        schema=section_schema(StructuredSettings),
    )
    # --- architecture: supp. "Architecture Details" / main Sec. 4.1 "Implementation Details" ---
    d_model: int = setting(32, '"32-dimensional hidden state"', minimum=1)
    nhead: int = setting(8, '"eight attention heads"', minimum=1)
    dim_feedforward: int = setting(64, '"64-dimensional feedforward layer"', minimum=1)
    dropout: float = setting(0.2, '"We apply a dropout rate of 0.2" (residual branches and feed-forward)')
    num_layers: int = setting(
        1,
        '"single-layer Transformer encoder" (LW); 5 = HC (supp. "Effect of Forecaster Capacity")',
        minimum=1,
    )
    attn_dropout: float = setting(
        0.0,
        "ours, not stated in the paper: no dropout on attention weights (PatchTST's default; its RevIN + flatten-head design matches)",
    )
    norm_first: bool = setting(
        True,
        "ours, not stated in the paper: pre-norm: keeps a linear path from the normalised inputs to the flatten head",
    )
    zero_init_residual: bool = setting(
        True,
        "ours, not stated in the paper: attention/FFN branches start at zero, i.e. training starts from a linear autoregressor",
    )
    # --- state normalisation: supp. "use instance normalization for each sequence" ---
    norm_eps: float = setting(
        1e-5,
        "variance floor (RevIN's eps): std = sqrt(var + eps), so static sequences stay finite",
        exclusive_minimum=0,
    )
    # --- objective: main "Training Objectives", supp. "Training Procedure and Inference Scheme" ---
    lambda_acc: float = setting(1.0, '"lambda_acc = 1.0 for all experiments"')
    loss_space: Literal["normalized", "pose"] = setting(
        "normalized", 'L_pred and L_acc on the instance-normalised state ("pose": world units); see module doc'
    )
    # --- masked input training: main "Masked Input Training", supp. "Training Procedure" ---
    masking: bool = setting(True, 'False = the "w/o masking" ablation (main Table "Ablation results", bottom)')
    mask_ratio_start: float = setting(
        0.4, '"a contiguous span covering 40--0% of the sequence is masked"', minimum=0, exclusive_maximum=1
    )
    mask_ratio_end: float = setting(
        0.0,
        "masked input training: main 'Masked Input Training', supp. 'Training Procedure'",
        minimum=0,
        exclusive_maximum=1,
    )
    mask_anneal_frac: float = setting(
        0.5, "ours: linear 40% -> 0% over the first half of training, unmasked after", exclusive_minimum=0, maximum=1
    )
    # --- optimisation: not in the paper; ours, sized for <= 60 s per group on 2 CPU cores ---
    iterations: int = setting(
        800,
        "Adam steps per fit of the learned forecaster, both modes (structured: the backtest fit, then the refit on "
        "every observed frame: with drift_check always, before the decision; without it, where the learned "
        "candidate keeps a weight). CPU: sized for the 60 s per group budget on 2 cores, a cost that does not grow "
        "with the group size",
        minimum=1,
    )
    batch_size: int = setting(
        128, "most Gaussians per step, drawn without replacement (epochs = iterations * batch / G)", minimum=1
    )
    batch_tokens: int = setting(
        4480,
        "pose tokens per step: batch = min(batch_size, batch_tokens // (T-1)), at least 16; 4480 = 128 x 35 (T = 36). Attention costs ~ batch x (T-1)^2, so long sequences take smaller batches and the step cost grows ~linearly in T instead of quadratically (0 = always batch_size)",
        minimum=0,
    )
    lr: float = setting(5e-3, "optimisation: not in the paper; ours, sized for <= 60 s per group on 2 CPU cores")
    lr_min: float = setting(1e-5, "cosine decay floor")
    weight_decay: float = setting(
        0.03,
        "L2 on all weights (Adam): a group's sequences are near copies after instance normalisation, so one-target "
        "training is under-determined, and without decay the flatten head's free directions make the "
        "autoregressive rollout blow up. Small, since stronger decay bends periodic motion",
        minimum=0,
    )
    grad_clip: float = setting(1.0, "global grad-norm clip")
    # --- runtime ---
    num_threads: int = setting(
        1, "tiny tensors: one intra-op thread is as fast and never oversubscribes parallel jobs (0 = torch's default)"
    )
    rollout_chunk: int = setting(16384, "Gaussians per forward pass at inference", minimum=1)


MOGAF_DEFAULTS: dict[str, Any] = defaults(MogafSettings)


def load_mogaf(section: Mapping[str, Any] | MogafSettings) -> tuple[MogafSettings, StructuredSettings]:
    """forecast.mogaf and its structured part (over its defaults), each checked
    against its bounds, then what the bounds cannot say: relations between
    settings. Both modes refuse a bad structured part (the config is one)."""
    net = load(MogafSettings, "forecast.mogaf", section)
    own = load(StructuredSettings, "forecast.mogaf.structured", net.structured or {})
    if net.d_model % net.nhead:
        raise MogafError(f"forecast.mogaf: d_model ({net.d_model}) must be divisible by nhead ({net.nhead})")
    if not (0.0 <= net.mask_ratio_end <= net.mask_ratio_start < 1.0):
        raise MogafError("forecast.mogaf: need 0 <= mask_ratio_end <= mask_ratio_start < 1")
    unknown = sorted(set(own.candidates) - set(STRUCTURED_CANDIDATES), key=str)
    if unknown or not own.candidates or len(set(own.candidates)) != len(own.candidates):
        raise MogafError(
            "forecast.mogaf.structured: candidates must be distinct names among "
            f"{', '.join(STRUCTURED_CANDIDATES)}, at least one; got {list(own.candidates)!r}"
        )
    if own.backtest_margin > 0 and own.combine != "select":
        raise MogafError(
            f"forecast.mogaf.structured: backtest_margin applies to combine: select only (combine is {own.combine})"
        )
    return net, own


@dataclass(frozen=True)
class ForecastMethod:
    """One forecast method: every list of methods derives from METHOD_TABLE."""

    name: str
    label: str  # in the tables and videos
    forecaster: str  # "module:Class" under mogaf.forecast, imported when a forecaster is made
    settings: type | None = None  # its settings dataclass (None: it takes none)
    section: str = ""  # the config section under forecast it reads ("": its own name)
    fixed: Mapping[str, Any] = dataclasses.field(default_factory=dict)  # settings it fixes, whatever the section says
    unread: tuple[str, ...] = ()  # keys of the section it does not read (changing them reruns nothing of it)
    inline: bool = False  # trains nothing: computed in the merge job, no per-group jobs
    table_rank: int = 0  # position in the tables (the papers' baselines first)


METHOD_TABLE: tuple[ForecastMethod, ...] = (
    ForecastMethod("mogaf", "MoGaF (Ours)", "transformer:MoGaFForecaster", MogafSettings, table_rank=2),
    ForecastMethod(
        "mogaf_paper",
        "MoGaF (paper)",
        "transformer:MoGaFPaperForecaster",
        MogafSettings,
        section="mogaf",
        fixed={"mode": "paper"},
        unread=("structured",),
        table_rank=3,
    ),
    ForecastMethod("gcn", "GSPred-SoM (GCN)", "gcn:GCNForecaster", GCNSettings, table_rank=0),
    ForecastMethod("ode", "ODE-GS-SoM (latent ODE)", "ode:LatentODEForecaster", ODESettings, table_rank=1),
    ForecastMethod("constant_velocity", "Const. velocity", "classical:ConstantVelocity", inline=True, table_rank=4),
    ForecastMethod("frozen", "Frozen", "classical:Frozen", inline=True, table_rank=5),
)
METHOD_BY_NAME: dict[str, ForecastMethod] = {m.name: m for m in METHOD_TABLE}

METHODS: tuple[str, ...] = tuple(m.name for m in METHOD_TABLE)
METHOD_SETTINGS: dict[str, type] = {m.name: m.settings for m in METHOD_TABLE if m.settings is not None}
PARAM_SECTIONS: dict[str, str] = {m.name: m.section for m in METHOD_TABLE if m.section}
FIXED_PARAMS: dict[str, dict[str, Any]] = {m.name: dict(m.fixed) for m in METHOD_TABLE if m.fixed}
UNREAD_PARAMS: dict[str, tuple[str, ...]] = {m.name: m.unread for m in METHOD_TABLE if m.unread}
INLINE_METHODS: tuple[str, ...] = tuple(m.name for m in METHOD_TABLE if m.inline)
TRAINED_METHODS: tuple[str, ...] = tuple(m.name for m in METHOD_TABLE if not m.inline)
# forecast.jobs: a Snakemake job per group and trained method, or one per method
# (mogaf.forecast.stage.merge_computes); the config schema's enum comes from here
JOB_LAYOUTS: tuple[str, ...] = ("per_group", "per_method")
METHOD_LABELS: dict[str, str] = {m.name: m.label for m in METHOD_TABLE}
METHOD_ORDER: list[str] = [m.name for m in sorted(METHOD_TABLE, key=lambda m: m.table_rank)]


def job_priority(base: int, method: str, start_first: Sequence[str]) -> float:
    """A forecast job's Snakemake priority: `base` (its rule's), plus a fraction
    below 1 that is larger the earlier `method` comes in forecast.start_first
    (0 for a method not listed), so where cores are short the listed methods'
    jobs start first, in that order, and never before a job of a higher rule
    priority. Scheduling only: no artefact depends on it."""
    order = list(start_first)
    if method not in order:
        return float(base)
    return base + (len(order) - order.index(method)) / (len(order) + 1)


# forecast.mogaf settings only the paper mode reads: the structured mode has
# its own weight decay, scales each window by its own spread and batches windows.
PAPER_ONLY = ("weight_decay", "loss_space", "batch_tokens", "norm_eps")
# forecast.mogaf.structured settings only the backtest reads.
BACKTEST_ONLY = (
    "candidates",
    "backtest_frac",
    "backtest_origins",
    "backtest_margin",
    "combine",
    "backtest_neighbors",
    "drift_check",
    "trend_window",
    "trend_half_life",
)
# forecast.mogaf.structured settings only the learned candidate reads
# (`context` also sizes the parabolas of braking and constant_acceleration).
LEARNED_ONLY = (
    "context",
    "horizon",
    "weight_decay",
    "max_train_windows",
    "drift_check",
    "backtest_margin",
    "refit_networks",
)
# forecast.mogaf settings of the masked input training, both modes.
MASKING_ONLY = ("mask_ratio_start", "mask_ratio_end", "mask_anneal_frac")


def _changed(settings: Any, default: Mapping[str, Any]) -> dict[str, Any]:
    """The settings whose value is not the default (candidates: as a set, their order is not read)."""
    out = {}
    for key, value in as_dict(settings).items():
        base = default[key]
        same = set(value) == set(base) if key == "candidates" else value == base
        if not same:
            out[key] = value
    return out


def _unread_by_mogaf(net: MogafSettings, own: StructuredSettings, changed: Mapping[str, Any]) -> dict[str, str]:
    """Which of the changed forecast.mogaf keys the `mogaf` method does not read, and why."""
    if net.mode == "paper":
        return {k: "mode is paper, which reads no structured setting" for k in changed if k.startswith("structured.")}
    why = dict.fromkeys(PAPER_ONLY, "only the paper mode reads it (mode is structured)")
    if not own.gate:
        why.update({f"structured.{k}": "gate is false (no backtest)" for k in BACKTEST_ONLY})
    if not {"linear_trend", "damped_trend"} & set(own.candidates):
        why.setdefault("structured.trend_window", "candidates has neither linear_trend nor damped_trend")
    if "damped_trend" not in own.candidates:
        why.setdefault("structured.trend_half_life", "candidates has no damped_trend")
    # a switch's own settings, unread where it is off
    for switch, off, keys in (
        ("nonrigid_motion", ("per_gaussian", "rigid_body"), ("rigid_parts", "parts_unexplained")),
        ("unobserved_motion", ("keep",), ("view_window", "observed_spread_deg")),
        ("track_agreement", ("keep",), ("track_steps", "min_tracks")),
    ):
        value = getattr(own, switch)
        for k in keys if value in off else ():
            reason = f"{switch} is {value}" + (", not rigid_parts" if switch == "nonrigid_motion" else "")
            why.setdefault(f"structured.{k}", reason)
    if own.combine == "select":
        why.setdefault("structured.backtest_neighbors", "combine is select, which decides per group")
        why.setdefault("structured.backtest_origins", "combine is select, which scores one window")
    if own.gate and "learned" not in own.candidates:
        for k in LEARNED_ONLY:
            if k != "context" or not {"braking", "constant_acceleration"} & set(own.candidates):
                why.setdefault(f"structured.{k}", "candidates has no learned")
        for k in changed:
            if "." not in k and k != "mode":
                why.setdefault(k, "candidates has no learned")
    return {k: r for k, r in why.items() if k in changed}


def _unread_by_row(method: ForecastMethod, changed: Mapping[str, Any]) -> dict[str, str]:
    """Which of the changed keys of its section a method with fixed or unread
    settings (mogaf_paper: paper mode whatever `mode` says, no `structured`) does not read."""
    skipped = (*method.fixed, *method.unread)
    return {
        k: f"{method.name} reads neither {' nor '.join(skipped)}"
        for k in changed
        if k in method.fixed or k.split(".", 1)[0] in method.unread
    }


def inert_settings(forecast: Mapping[str, Any]) -> list[tuple[str, str]]:
    """forecast.mogaf settings set away from their defaults that no listed
    method reads (`forecast`: the config's forecast section, `methods` and
    `mogaf`): (the key under forecast.mogaf, e.g. "structured.trend_window";
    a line saying its value and why), by key. `mogaf_paper` reads forecast.mogaf
    too, in paper mode and without `structured`.

    Not an error, unlike a select-only margin under the weighted blend: an
    ablation variant switches the setting that makes such a value act again
    (config/ablations.yaml), and a sweep must not stop for it; but a value
    that changes nothing should not look like a measured setting."""
    net, own = load_mogaf(forecast.get("mogaf") or {})
    changed = {k: v for k, v in _changed(net, MOGAF_DEFAULTS).items() if k != "structured"}
    changed.update({f"structured.{k}": v for k, v in _changed(own, STRUCTURED_DEFAULTS).items()})
    methods = list(forecast.get("methods") or ())
    section_readers = [m.name for m in METHOD_TABLE if (m.section or m.name) == "mogaf"]
    readers = [m for m in section_readers if m in methods]
    if not readers:
        why = dict.fromkeys(changed, f"forecast.methods has neither {' nor '.join(section_readers)}")
    else:
        # a value is without effect only if every method reading forecast.mogaf leaves it
        unread = [
            _unread_by_mogaf(net, own, changed) if m == "mogaf" else _unread_by_row(METHOD_BY_NAME[m], changed)
            for m in readers
        ]
        why = {k: r for k, r in unread[0].items() if all(k in u for u in unread)}
        if not net.masking:  # neither reader's network masks its inputs, in either mode
            why.update({k: "masking is false" for k in MASKING_ONLY if k in changed})
    return [(k, f"forecast.mogaf.{k} = {changed[k]!r} has no effect: {why[k]}") for k in sorted(why)]


def section_params(method: str, section: Mapping[str, Any] | None) -> dict[str, Any]:
    """What `method` reads of its config section (forecast.<param_section(method)>)."""
    unread = UNREAD_PARAMS.get(method, ())
    return {**{k: v for k, v in dict(section or {}).items() if k not in unread}, **FIXED_PARAMS.get(method, {})}


def param_section(method: str) -> str:
    """The `forecast.<section>` holding `method`'s settings."""
    return PARAM_SECTIONS.get(method, method)
