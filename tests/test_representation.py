"""mogaf.representation's rotation conversions against their references."""

from __future__ import annotations

import pytest
import torch

from mogaf.eager_roma import load as load_roma
from mogaf.representation import first_argmax, matrix_to_quat, quat_to_matrix, rotmat_to_xyzw


def _rotations(n: int, seed: int) -> torch.Tensor:
    roma = load_roma()
    gen = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    R = roma.unitquat_to_rotmat(q / q.norm(dim=-1, keepdim=True))
    half_turns = roma.rotvec_to_rotmat(torch.pi * torch.eye(3, dtype=torch.float64))  # two diagonal entries tie
    return torch.cat([R, half_turns, torch.eye(3, dtype=torch.float64)[None]])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("jitter", [0.0, 1e-3])
def test_rotmat_to_xyzw_is_romas_method_bit_for_bit_with_its_gradients(dtype, jitter):
    R = _rotations(20000, 0)
    R = (R + jitter * torch.randn(R.shape, generator=torch.Generator().manual_seed(1), dtype=R.dtype)).to(dtype)
    weights = torch.randn(R.shape[0], 4, generator=torch.Generator().manual_seed(2), dtype=dtype)
    outs = []
    for convert in (load_roma().rotmat_to_unitquat, rotmat_to_xyzw):
        M = R.clone().requires_grad_()
        q = convert(M)
        (grad,) = torch.autograd.grad((q * weights).sum(), M)
        outs.append((q.detach(), grad))
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])


def test_matrix_to_quat_inverts_quat_to_matrix_with_w_non_negative():
    q = torch.randn(500, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    back = matrix_to_quat(quat_to_matrix(q))
    assert torch.allclose(back, q, atol=1e-12) and bool((back[:, 0] >= 0).all())


def test_first_argmax_is_torchs_argmax_with_ties_infinities_and_nans():
    nan, inf = float("nan"), float("inf")
    rows = [
        [1.0, 3.0, 3.0, 2.0],
        [2.0, 2.0, 2.0, 2.0],
        [nan, 1.0, 2.0, 3.0],
        [1.0, nan, 5.0, nan],
        [-inf, -inf, -inf, -inf],
        [0.0, inf, inf, -1.0],
        [-1.0, -0.5, -2.0, -0.5],
    ]
    v = torch.tensor(rows)
    assert first_argmax(v).tolist() == torch.argmax(v, dim=-1).tolist()
    rand = torch.randint(0, 4, (3000, 4), generator=torch.Generator().manual_seed(4)).float()  # many ties
    assert torch.equal(first_argmax(rand), torch.argmax(rand, dim=-1))
    assert torch.equal(first_argmax(rand.reshape(10, 300, 4)), torch.argmax(rand.reshape(10, 300, 4), dim=-1))
