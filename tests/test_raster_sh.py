"""Spherical-harmonics colour: constants, 3DGS sign conventions, the renderer's +0.5 and clamp."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.special import sph_harm_y

from baselines.render import RGB2SH, SH2RGB, eval_sh, sh_to_rgb
from baselines.render.sh import SH_C0, SH_C1, sh_basis


def _unit(v) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.as_tensor(v, dtype=torch.float64), dim=-1)


def _scipy_basis(degree: int, dirs: np.ndarray) -> np.ndarray:
    """3DGS's basis from scipy: index l^2 + l + m holds sqrt(2) Im Y_l^|m| (m < 0), Y_l^0, or
    sqrt(2) Re Y_l^m (m > 0), with scipy's complex Y (Condon-Shortley phase included). That is the
    textbook real basis times (-1)^m, which is the sign convention 3DGS's constants encode."""
    theta = np.arccos(np.clip(dirs[:, 2], -1, 1))  # polar angle
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])
    cols = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            y = sph_harm_y(l, abs(m), theta, phi)
            cols.append(np.sqrt(2) * y.imag if m < 0 else (y.real if m == 0 else np.sqrt(2) * y.real))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_basis_matches_scipy_with_3dgs_signs(degree):
    dirs = _unit(torch.randn(64, 3, generator=torch.Generator().manual_seed(degree)))
    np.testing.assert_allclose(sh_basis(degree, dirs).numpy(), _scipy_basis(degree, dirs.numpy()), atol=1e-12)


def test_basis_is_orthonormal_on_the_sphere():
    # Gauss-Legendre in cos(theta) x uniform phi integrates products of degree <= 6 exactly.
    nodes, weights = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * (2 * np.pi / 16)
    z, p = np.meshgrid(nodes, phi, indexing="ij")
    r = np.sqrt(1 - z**2)
    dirs = torch.tensor(np.stack([r * np.cos(p), r * np.sin(p), z], -1).reshape(-1, 3))
    w = torch.tensor((weights[:, None] * np.full(16, 2 * np.pi / 16)[None, :]).reshape(-1))
    basis = sh_basis(3, dirs)
    gram = basis.T @ (basis * w[:, None])
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-12, rtol=0)


def test_degree_one_signs_by_hand():
    # 3DGS: coefficient 1 multiplies -C1 y, coefficient 2 +C1 z, coefficient 3 -C1 x.
    sh = torch.zeros(3, 4, 3, dtype=torch.float64)
    sh[0, 1, 0] = sh[1, 2, 0] = sh[2, 3, 0] = 1.0
    dirs = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    assert eval_sh(1, sh, dirs)[:, 0].tolist() == [-SH_C1, SH_C1, -SH_C1]


def test_dc_round_trip_and_active_degree():
    rgb = torch.rand(10, 3, dtype=torch.float64)
    torch.testing.assert_close(SH2RGB(RGB2SH(rgb)), rgb)
    sh = torch.randn(10, 16, 3, dtype=torch.float64)
    dirs = _unit(torch.randn(10, 3, dtype=torch.float64))
    # Degree 0 reads only the DC term; a lower active degree ignores the higher coefficients.
    torch.testing.assert_close(eval_sh(0, sh, dirs), SH_C0 * sh[:, 0])
    torch.testing.assert_close(eval_sh(1, sh, dirs), eval_sh(1, sh[:, :4], dirs))
    assert not torch.allclose(eval_sh(3, sh, dirs), eval_sh(2, sh, dirs))


def test_sh_to_rgb_is_the_renderers_colour():
    g = torch.Generator().manual_seed(1)
    sh = torch.randn(50, 16, 3, generator=g, dtype=torch.float64)
    means = torch.randn(50, 3, generator=g, dtype=torch.float64)
    centre = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    colour = sh_to_rgb(sh, means, centre, 3)
    dirs = (means - centre) / (means - centre).norm(dim=-1, keepdim=True)
    expected = torch.clamp_min(eval_sh(3, sh, dirs) + 0.5, 0.0)
    torch.testing.assert_close(colour, expected)
    assert (colour == 0).any() and (colour > 0).any()  # the clamp is exercised
    # Only the direction matters (not the distance), and the clamp stops gradients.
    far = centre + 7.0 * (means - centre)
    torch.testing.assert_close(sh_to_rgb(sh, far, centre, 3), colour)
    sh.requires_grad_(True)
    sh_to_rgb(sh, means, centre, 3).sum().backward()
    clamped = expected == 0
    assert (sh.grad[:, 0][clamped] == 0).all() and (sh.grad[:, 0][~clamped] != 0).all()


def test_gaussian_at_the_camera_centre_stays_finite():
    sh = torch.randn(2, 4, 3, requires_grad=True)
    means = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], requires_grad=True)
    colour = sh_to_rgb(sh, means, torch.zeros(3), 1)
    colour.sum().backward()
    assert torch.isfinite(colour).all() and torch.isfinite(means.grad).all() and torch.isfinite(sh.grad).all()


@pytest.mark.parametrize("call, culprit", [
    (lambda: eval_sh(4, torch.zeros(2, 25, 3), torch.zeros(2, 3)), "degree"),
    (lambda: eval_sh(2, torch.zeros(2, 4, 3), torch.zeros(2, 3)), "sh"),
    (lambda: eval_sh(1, torch.zeros(2, 4, 3), torch.zeros(3, 3)), "dirs"),
    (lambda: sh_to_rgb(torch.zeros(2, 4, 3), torch.zeros(2, 3), torch.zeros(1, 3), 1), "camera_center"),
])
def test_bad_inputs(call, culprit):
    with pytest.raises(ValueError, match=culprit):
        call()
