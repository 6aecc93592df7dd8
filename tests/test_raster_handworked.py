"""Hand-worked tiny images: every expected value below is derived by hand in the comments."""
from __future__ import annotations

import math

import pytest
import torch

from baselines.render import rasterize
from raster_cases import camera_space_scene, over_all_compositors, render_with, screen_projection

IDENTITY_CONIC = [1.0, 0.0, 1.0]  # sigma = (dx^2 + dy^2) / 2


def _offsets(width: int, height: int, mx: float, my: float) -> tuple[torch.Tensor, torch.Tensor]:
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                            torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    return xs - mx, ys - my


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_single_gaussian_through_the_full_pipeline(backend):
    # f = 8, principal point (2.5, 2) in a 5x4 image. The mean (0, -0.125, 2) projects to
    # (8 * 0 / 2 + 2.5, 8 * -0.125 / 2 + 2) = (2.5, 1.5): the centre of pixel (row 1, col 2).
    # J = [[4, 0, 0], [0, 4, 0.25]] (x = 0, -fy y / z^2 = 0.25), Sigma_cam = 0.25^2 I, so
    # cov2d = 0.0625 J J^T + 0.3 I = diag(1.3, 0.0625 * 16.0625 + 0.3) = diag(1.3, 1.30390625).
    o, feature = 0.6, torch.tensor([0.2, 0.4, 0.8])
    scene = camera_space_scene(torch.tensor([[0.0, -0.125, 2.0]]), torch.full((1, 3), 0.25), torch.tensor([o]),
                               feature[None], width=5, height=4, focal=8.0)
    scene.K[1, 2] = 2.0
    image, depth, alpha, meta = rasterize(*scene.args(), backend=backend)

    assert meta.means2d.tolist() == [[2.5, 1.5]]
    assert meta.depths.tolist() == [2.0]
    torch.testing.assert_close(meta.cov2d[0].double(), torch.tensor([[1.3, 0.0], [0.0, 1.30390625]], dtype=torch.float64))
    # At the centre sigma = 0: alpha = o exactly, colour = o * feature, depth = o z / o = z.
    assert alpha[1, 2, 0] == torch.tensor(o)
    assert torch.equal(image[1, 2], torch.tensor(o) * feature)
    assert depth[1, 2, 0] == 2.0
    # Elsewhere alpha = o exp(-(dx^2 / 1.3 + dy^2 / 1.30390625) / 2), or 0 below 1/255.
    dx, dy = _offsets(5, 4, 2.5, 1.5)
    expected = o * torch.exp(-0.5 * (dx**2 / 1.3 + dy**2 / 1.30390625))
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    torch.testing.assert_close(alpha[..., 0].double(), expected, atol=1e-6, rtol=0)
    torch.testing.assert_close(image.double(), expected[..., None] * feature.double(), atol=1e-6, rtol=0)
    covered = expected > 0
    torch.testing.assert_close(depth[..., 0][covered], torch.full((int(covered.sum()),), 2.0))


@over_all_compositors
def test_two_overlapping_gaussians_front_one_dominates(compositor):
    # Both on the centre of pixel (1, 2), identity conics. Index 0 is the BACK one (z = 5,
    # o = 0.8, green), index 1 the front one (z = 2, o = 0.5, red): order must come from depth.
    proj = screen_projection([[2.5, 1.5], [2.5, 1.5]], [IDENTITY_CONIC] * 2, [5.0, 2.0], [0.8, 0.5], 12, 9)
    opac = torch.tensor([0.8, 0.5])
    feats = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    bg = torch.tensor([0.1, 0.2, 0.3])
    image, depth, alpha = render_with(compositor, proj, opac, feats, 12, 9, background=bg)
    # Centre: front alpha 0.5, then T = 0.5 and the back one adds 0.5 * 0.8 = 0.4.
    # colour = (0.5, 0.4, 0) + (1 - 0.9) * bg; depth = (0.5 * 2 + 0.4 * 5) / 0.9 = 3 / 0.9.
    torch.testing.assert_close(alpha[1, 2, 0], torch.tensor(0.9), atol=1e-7, rtol=0)
    torch.testing.assert_close(image[1, 2], torch.tensor([0.5, 0.4, 0.0]) + 0.1 * bg, atol=1e-7, rtol=0)
    torch.testing.assert_close(depth[1, 2, 0], torch.tensor(3.0 / 0.9), atol=1e-6, rtol=0)
    # One pixel right (dx = 1): a1 = 0.5 e^-0.5, a2 = 0.8 e^-0.5; colour (a1, (1 - a1) a2, 0).
    a1, a2 = 0.5 * math.exp(-0.5), 0.8 * math.exp(-0.5)
    a = a1 + (1 - a1) * a2
    torch.testing.assert_close(image[1, 3].double(), torch.tensor([a1, (1 - a1) * a2, 0.0], dtype=torch.float64)
                               + (1 - a) * bg.double(), atol=1e-6, rtol=0)
    # Far corner (dx = 9, dy = 7): no Gaussian reaches it, so background exactly, alpha and depth 0.
    assert torch.equal(image[8, 11], bg)
    assert alpha[8, 11, 0] == 0.0 and depth[8, 11, 0] == 0.0


@over_all_compositors
def test_depth_ties_keep_index_order(compositor):
    # Two coincident Gaussians at the same depth: the lower index is in front (a stable sort).
    # At the centre of pixel (1, 2) alpha = 0.9 for both: index 0 gives 0.9 red, index 1 then
    # 0.1 * 0.9 = 0.09 green; in the other order the colours would swap.
    proj = screen_projection([[2.5, 1.5], [2.5, 1.5]], [IDENTITY_CONIC] * 2, [3.0, 3.0], [0.9, 0.9], 6, 4)
    image, alpha = compositor(proj, torch.tensor([0.9, 0.9]), torch.tensor([[1.0, 0.0], [0.0, 1.0]]), 6, 4)
    torch.testing.assert_close(image[1, 2], torch.tensor([0.9, 0.09]), atol=1e-7, rtol=0)
    torch.testing.assert_close(alpha[1, 2, 0], torch.tensor(0.99), atol=1e-7, rtol=0)


@over_all_compositors
def test_alpha_is_clamped_at_0_999(compositor):
    # Opacity 1 at the centre of pixel (1, 2): o exp(0) = 1 is clamped to 0.999; one pixel right
    # exp(-0.5) = 0.607 is not clamped.
    proj = screen_projection([[2.5, 1.5]], [IDENTITY_CONIC], [1.0], [1.0], 6, 4)
    feats = torch.tensor([[0.5, 1.0]])
    image, alpha = compositor(proj, torch.tensor([1.0]), feats, 6, 4)
    assert alpha[1, 2, 0] == torch.tensor(0.999)
    assert torch.equal(image[1, 2], torch.tensor(0.999) * feats[0])
    torch.testing.assert_close(alpha[1, 3, 0], torch.tensor(math.exp(-0.5)), atol=1e-7, rtol=0)


@over_all_compositors
def test_alphas_below_1_over_255_are_skipped(compositor):
    # o = 0.5, identity conic at (2.5, 1.5): offset (3, 0) gives 0.5 e^-4.5 = 0.00555 >= 1/255,
    # offset (3, 1) gives 0.5 e^-5 = 0.00337 < 1/255 = 0.00392, so exactly 0 there.
    proj = screen_projection([[2.5, 1.5]], [IDENTITY_CONIC], [1.0], [0.5], 12, 9)
    image, alpha = compositor(proj, torch.tensor([0.5]), torch.ones(1, 1), 12, 9)
    torch.testing.assert_close(alpha[1, 5, 0], torch.tensor(0.5 * math.exp(-4.5)), atol=1e-8, rtol=0)
    assert alpha[2, 5, 0] == 0.0 and image[2, 5, 0] == 0.0
    dx, dy = _offsets(12, 9, 2.5, 1.5)
    raw = 0.5 * torch.exp(-0.5 * (dx**2 + dy**2))
    assert ((raw > 0) & (raw < 1 / 255)).any()  # the rule is exercised
    expected = torch.where(raw >= 1 / 255, raw, torch.zeros_like(raw))
    torch.testing.assert_close(alpha[..., 0].double(), expected, atol=1e-7, rtol=0)


@over_all_compositors
def test_skipped_gaussian_does_not_dim_the_ones_behind(compositor):
    # A front Gaussian whose alpha at pixel (2, 5) is below 1/255 (see the test above) must leave
    # the transmittance at 1 there: the pixel shows the back Gaussian alone.
    proj = screen_projection([[2.5, 1.5], [5.5, 2.5]], [IDENTITY_CONIC] * 2, [1.0, 3.0], [0.5, 0.7], 12, 9)
    feats = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    image, alpha = compositor(proj, torch.tensor([0.5, 0.7]), feats, 12, 9)
    assert alpha[2, 5, 0] == torch.tensor(0.7)
    assert torch.equal(image[2, 5], torch.tensor([0.0, 0.7]))


@over_all_compositors
@pytest.mark.parametrize("opacity, composited, composited_next", [(0.5, 13, 20), (0.75, 6, 15)])
def test_transmittance_stop_at_the_hand_computed_index(compositor, opacity, composited, composited_next):
    # 20 Gaussians stacked on the centre of pixel (1, 2), depths 1..20. At the centre every alpha
    # is o, so after k of them T = (1 - o)^k. o = 0.5: T = 2^-13 = 1.2e-4 > 1e-4 after 13, and the
    # 14th would bring 6.1e-5 <= 1e-4, so exactly 13 are composited. o = 0.75: 0.25^6 = 2.4e-4,
    # 0.25^7 = 6.1e-5, so 6. Channel 1 marks the Gaussians past the stop: it must stay 0 there.
    n = 20
    proj = screen_projection([[2.5, 1.5]] * n, [IDENTITY_CONIC] * n, list(range(1, n + 1)), [opacity] * n, 6, 4)
    flag = (torch.arange(n) >= composited).float()
    feats = torch.stack([torch.ones(n), flag], dim=1)
    image, alpha = compositor(proj, torch.full((n,), opacity), feats, 6, 4)
    t_final = (1 - opacity) ** composited
    torch.testing.assert_close(alpha[1, 2, 0], torch.tensor(1 - t_final), atol=1e-7, rtol=0)
    torch.testing.assert_close(image[1, 2, 0], torch.tensor(1 - t_final), atol=1e-7, rtol=0)
    assert image[1, 2, 1] == 0.0
    # One pixel right every alpha is a = o e^-0.5, so the stop comes later (per pixel).
    # o = 0.5: a = 0.3033, (1 - a)^20 = 7.2e-4 > 1e-4: no stop, all 20 composited.
    # o = 0.75: a = 0.4549, (1 - a)^15 = 1.12e-4 > 1e-4 >= (1 - a)^16 = 6.1e-5: 15 composited.
    # Channel 0 = 1 - (1 - a)^k; channel 1 collects the Gaussians `composited`..k-1.
    a = opacity * math.exp(-0.5)
    k = composited_next
    torch.testing.assert_close(image[1, 3, 0].double(), torch.tensor(1 - (1 - a) ** k, dtype=torch.float64),
                               atol=1e-6, rtol=0)
    torch.testing.assert_close(image[1, 3, 1].double(),
                               torch.tensor((1 - a) ** composited - (1 - a) ** k, dtype=torch.float64),
                               atol=1e-6, rtol=0)
