"""MoGaF's settings as its forecasters read them: forecast.mogaf (both modes)
and its `structured` part, loaded and checked once (MogafRun)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from mogaf.forecast.base import merge_params
from mogaf.forecast.params import MogafSettings, StructuredSettings, load_mogaf


@dataclass(frozen=True)
class MogafRun:
    """What a MoGaF forecaster runs with: the network, masking and optimiser
    settings of forecast.mogaf (`net`, both modes) and forecast.mogaf.structured
    (`own`, the structured mode's; its weight_decay replaces the paper mode's).
    Either mode refuses a bad structured part: the config is one."""

    net: MogafSettings
    own: StructuredSettings


def load_run(
    name: str, defaults: Mapping[str, Any], params: Mapping[str, Any] | MogafRun | None, fixed: Mapping[str, Any]
) -> MogafRun:
    """`params` over `defaults`, with `fixed` over both (mogaf_paper: mode paper,
    whatever the section says), each check made once: every setting against
    its bounds (base.merge_params), then the structured part and the
    relations between settings (params.load_mogaf). A MogafRun is taken as
    it is (its `fixed` settings set)."""
    if isinstance(params, MogafRun):
        return replace(params, net=replace(params.net, **fixed)) if fixed else params
    net = MogafSettings(**{**merge_params(name, defaults, params), **fixed})
    return MogafRun(*load_mogaf(net))
