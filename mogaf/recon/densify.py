"""Adaptive density control (3DGS / Shape-of-Motion rules).

Statistics, accumulated over the views of every step, for every Gaussian
(fg rows then bg rows, the rendering order):
  grad_acc  sum of |d loss / d means2d| in NDC units (pixels * W/2, H/2,
            times the batch size, as SoM does), over views where it is drawn
  count     number of those views
  max_radii largest screen radius / max(W, H)

At a control step:
  grad_avg = grad_acc / count
  split  = grad_avg > thr_grad and (max scale > thr_scale * extent or max_radii > thr_screen)
  clone  = grad_avg > thr_grad and max scale <= thr_scale * extent
  cull   = opacity < thr_opacity, and after the first opacity reset (as in SoM)
           also max scale > thr_cull * extent or max_radii > thr_cull_screen
Split Gaussians are replaced by two copies with scales / 1.6 and means drawn
from the Gaussian (3DGS); clones are exact copies. New rows get zero Adam
moments. A budget (max Gaussians) keeps the highest-gradient candidates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..representation import quat_to_matrix
from .model import ReconModel

SPLIT_SCALE = 1.6


@dataclass
class DensifyRules:
    grad_threshold: float = 0.0002
    scale_threshold: float = 0.01  # x extent
    screen_threshold: float = 0.05
    cull_opacity: float = 0.1
    cull_scale: float = 0.5  # x extent
    cull_screen: float = 0.15
    use_screen: bool = True
    cull_by_size: bool = True  # SoM culls by size only after the first opacity reset
    extent: float = 1.0
    max_gaussians: int = 1 << 30


class DensityStats:
    def __init__(self, n: int):
        self.grad_acc = torch.zeros(n, dtype=torch.float64)
        self.count = torch.zeros(n, dtype=torch.int64)
        self.max_radii = torch.zeros(n, dtype=torch.float32)
        # kept on the CPU (float64 sums: order-stable and exact enough)

    def __len__(self) -> int:
        return int(self.count.shape[0])

    def reset(self, n: int | None = None) -> None:
        self.__init__(len(self) if n is None else n)

    @torch.no_grad()
    def accumulate(
        self, grad2d: torch.Tensor, radii: torch.Tensor, width: int, height: int, batch_size: int = 1
    ) -> None:
        """Add one view: grad2d (N,2) gradient of the loss w.r.t. means2d (pixels), radii (N,)."""
        radii = radii.detach().cpu()  # the statistics live on the CPU, whatever renders
        sel = radii > 0
        if grad2d is None or not bool(sel.any()):
            return
        g = grad2d.detach().cpu().to(torch.float64).clone()
        g[:, 0] *= width / 2.0 * batch_size
        g[:, 1] *= height / 2.0 * batch_size
        idx = torch.nonzero(sel, as_tuple=False).squeeze(1)
        self.grad_acc.index_add_(0, idx, g[idx].norm(dim=-1))
        self.count.index_add_(0, idx, torch.ones_like(idx))
        r = radii[idx].to(torch.float32) / float(max(width, height))
        self.max_radii[idx] = torch.maximum(self.max_radii[idx], r)

    def grad_avg(self) -> torch.Tensor:
        return (self.grad_acc / self.count.clamp_min(1).to(torch.float64)).to(torch.float32)

    def state(self) -> dict[str, torch.Tensor]:
        return {"grad_acc": self.grad_acc.clone(), "count": self.count.clone(), "max_radii": self.max_radii.clone()}

    def load(self, state: dict[str, torch.Tensor]) -> None:
        self.grad_acc = state["grad_acc"].clone()
        self.count = state["count"].clone()
        self.max_radii = state["max_radii"].clone()


def select_densify(
    grad_avg: torch.Tensor, max_scale: torch.Tensor, max_radii: torch.Tensor, rules: DensifyRules, n_current: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Boolean (split, clone) masks, trimmed to the Gaussian budget (highest gradient first)."""
    high = grad_avg > rules.grad_threshold
    big = max_scale > rules.scale_threshold * rules.extent
    if rules.use_screen:
        big_screen = max_radii > rules.screen_threshold
    else:
        big_screen = torch.zeros_like(high)
    split = high & (big | big_screen)
    clone = high & ~big & ~split
    room = rules.max_gaussians - n_current
    n_new = int(split.sum() + clone.sum())
    if n_new > room:
        cand = torch.nonzero(split | clone, as_tuple=False).squeeze(1)
        keep = max(room, 0)
        order = torch.argsort(-grad_avg[cand], stable=True)[:keep]
        chosen = torch.zeros_like(high)
        chosen[cand[order]] = True
        split &= chosen
        clone &= chosen
    return split, clone


def select_cull(
    opacity: torch.Tensor,
    max_scale: torch.Tensor,
    max_radii: torch.Tensor,
    rules: DensifyRules,
    extent_factor: torch.Tensor | None = None,
) -> torch.Tensor:
    cull = opacity < rules.cull_opacity
    if not rules.cull_by_size:
        return cull
    thr = rules.cull_scale * rules.extent
    if extent_factor is not None:
        thr = thr * extent_factor
    cull |= max_scale > thr
    if rules.use_screen:
        cull |= max_radii > rules.cull_screen
    return cull


# ------------------------------------------------------------------ optimiser surgery
def _swap_param(opt: torch.optim.Optimizer, old: torch.nn.Parameter, new: torch.nn.Parameter, rows) -> None:
    """Point `opt` at `new`; its per-row Adam state is rows(state_tensor) (or dropped if absent)."""
    group = opt.param_groups[0]
    state = opt.state.pop(old, None)
    group["params"] = [new]
    if state:
        new_state = {}
        for k, v in state.items():
            if k == "step" or not torch.is_tensor(v) or v.ndim == 0:
                new_state[k] = v
            else:
                new_state[k] = rows(v)
        opt.state[new] = new_state


@torch.no_grad()
def apply_densify(
    model: ReconModel,
    optimizers: dict[str, torch.optim.Optimizer],
    part: str,
    split: torch.Tensor,
    clone: torch.Tensor,
    gen: torch.Generator,
) -> tuple[int, int]:
    """Rows become [kept (not split), clones, split copy 1, split copy 2]."""
    g = getattr(model, part)
    n_split, n_clone = int(split.sum()), int(clone.sum())
    if n_split == 0 and n_clone == 0:
        return 0, 0
    dev = g.get("means").device
    split, clone = split.to(dev), clone.to(dev)
    keep = ~split
    means = g.get("means")
    scales = torch.exp(g.get("log_scales"))
    noise = torch.randn((2, n_split, 3), generator=gen, dtype=means.dtype).to(means.device)
    R = quat_to_matrix(g.get("quats")[split])
    offsets = torch.einsum("nij,knj->kni", R, noise * scales[split][None])
    for name, p in list(g.params.items()):
        x = p.detach()
        xs = x[split]
        if name == "means":
            s1, s2 = xs + offsets[0], xs + offsets[1]
        elif name == "log_scales":
            s1 = s2 = xs - math.log(SPLIT_SCALE)
        else:
            s1 = s2 = xs
        new = torch.cat([x[keep], x[clone], s1, s2], dim=0)
        newp = g.replace(name, new)
        n_extra = n_clone + 2 * n_split

        def rows(v: torch.Tensor, n_extra=n_extra) -> torch.Tensor:
            return torch.cat([v[keep], v.new_zeros((n_extra,) + v.shape[1:])], dim=0)

        _swap_param(optimizers[f"{part}.{name}"], p, newp, rows)
    g.rows_aux(lambda v: torch.cat([v[keep], v[clone], v[split], v[split]], dim=0))
    return n_split, n_clone


@torch.no_grad()
def apply_cull(model: ReconModel, optimizers: dict[str, torch.optim.Optimizer], part: str, cull: torch.Tensor) -> int:
    g = getattr(model, part)
    n = int(cull.sum())
    if n == 0:
        return 0
    keep = ~cull.to(g.get("means").device)
    for name, p in list(g.params.items()):
        newp = g.replace(name, p.detach()[keep])
        _swap_param(optimizers[f"{part}.{name}"], p, newp, lambda v: v[keep])
    g.rows_aux(lambda v: v[keep])
    return n


def reorder_stats_after_densify(stats: torch.Tensor, split: torch.Tensor, clone: torch.Tensor) -> torch.Tensor:
    return torch.cat([stats[~split], stats[clone], stats[split], stats[split]], dim=0)


@torch.no_grad()
def control_step(
    model: ReconModel,
    optimizers: dict[str, torch.optim.Optimizer],
    stats: DensityStats,
    rules: DensifyRules,
    gen: torch.Generator,
    *,
    densify: bool = True,
    cull: bool = True,
) -> dict[str, int]:
    """One densify + cull pass over fg and bg; resets the statistics. Returns counts."""
    out = {"split": 0, "clone": 0, "culled": 0}
    nf = model.num_fg
    grad = stats.grad_avg()
    radii = stats.max_radii
    parts = [("fg", slice(0, nf))]
    if model.bg is not None:
        parts.append(("bg", slice(nf, nf + model.num_bg)))
    if densify:
        n_cur = model.num_gaussians
        masks = {}
        # Budget is shared: decide on the concatenation.
        max_scale = torch.cat([getattr(model, p).scales().amax(-1).cpu() for p, _ in parts])
        split, clone = select_densify(grad, max_scale, radii, rules, n_cur)
        for p, sl in parts:
            masks[p] = (split[sl], clone[sl])
        for p, _ in parts:
            s, c = masks[p]
            ns, nc = apply_densify(model, optimizers, p, s, c, gen)
            out["split"] += ns
            out["clone"] += nc
        # keep statistics aligned (their max_radii matter for culling)
        new_radii = []
        for p, sl in parts:
            s, c = masks[p]
            new_radii.append(reorder_stats_after_densify(radii[sl], s, c))
        radii = torch.cat(new_radii)
        nf = model.num_fg
        parts = [("fg", slice(0, nf))] + ([("bg", slice(nf, nf + model.num_bg))] if model.bg is not None else [])
    if cull:
        removed = []
        for p, sl in parts:
            g = getattr(model, p)
            factor = None
            c = select_cull(g.opacities().cpu(), g.scales().amax(-1).cpu(), radii[sl], rules, factor)
            # never remove every Gaussian of a part
            if bool(c.all()):
                c[torch.argmax(g.opacities())] = False
            removed.append((p, c))
        for p, c in removed:
            out["culled"] += apply_cull(model, optimizers, p, c)
    stats.reset(model.num_gaussians)
    return out
