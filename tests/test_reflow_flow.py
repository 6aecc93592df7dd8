"""Full flow, camera flow, warping and the photometric loss of flow matching (reflow_plugin)."""
from __future__ import annotations

import math

import pytest
import torch

from baselines.render import composite, project_gaussians
from reflow_plugin.flow import (camera_flow, flow_features, full_flow, full_flow_dense, pixel_grid, sqrtm_spd2)
from reflow_plugin.warp import backward_warp, gaussian_blur, occlusion_mask, photometric_loss
from tests.raster_cases import intrinsics, look_from, random_scene

W, H = 24, 20


def _render_flow(means_a, means_b, quats, scales_a, scales_b, opacities, viewmat_a, viewmat_b, K, width=W, height=H,
                 backend="reference", min_alpha=0.5):
    pa = project_gaussians(means_a, quats, scales_a, viewmat_a, K, width, height, opacities=opacities, backend=backend)
    pb = project_gaussians(means_b, quats, scales_b, viewmat_b, K, width, height, opacities=opacities, backend=backend)
    maps, depth, alpha = composite(pa, opacities, flow_features(pa, pb), width, height, backend=backend)
    flow, valid = full_flow(maps, alpha, min_alpha)
    return flow, valid, pa, pb, depth, alpha


def _one_gaussian(dtype=torch.float32):
    K = intrinsics(W, H, focal=20.0, dtype=dtype)
    # mean projecting to the centre of pixel (row 10, col 12): x = 12.5, y = 10.5
    z = 4.0
    mean = torch.tensor([[(12.5 - K[0, 2]) / K[0, 0] * z, (10.5 - K[1, 2]) / K[1, 1] * z, z]], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype)
    scales = torch.full((1, 3), 0.8, dtype=dtype)
    return K, mean, quats, scales, torch.tensor([0.99], dtype=dtype)


def test_sqrtm_spd2_squares_back():
    g = torch.Generator().manual_seed(0)
    m = torch.randn(50, 2, 2, generator=g, dtype=torch.float64)
    spd = m @ m.transpose(1, 2) + 0.01 * torch.eye(2, dtype=torch.float64)
    a, b, c = sqrtm_spd2(spd[:, 0, 0], spd[:, 0, 1], spd[:, 1, 1])
    root = torch.stack([a, b, b, c], -1).reshape(-1, 2, 2)
    torch.testing.assert_close(root @ root, spd, rtol=1e-9, atol=1e-9)
    assert (torch.linalg.eigvalsh(root) > 0).all()
    singular = sqrtm_spd2(torch.tensor([1.0]), torch.tensor([1.0]), torch.tensor([1.0]))
    assert all(torch.isfinite(v).all() for v in singular)


def test_translated_gaussian_flow_is_its_displacement():
    K, mean, quats, scales, opacity = _one_gaussian()
    shift = torch.tensor([[0.3, -0.2, 0.0]])  # world units at z = 4 (fixed camera)
    flow, valid, pa, pb, _, _ = _render_flow(mean, mean + shift, quats, scales, scales, opacity,
                                             torch.eye(4), torch.eye(4), K)
    expected = (pb.means2d - pa.means2d)[0]
    assert valid[10, 12]
    torch.testing.assert_close(flow[10, 12], expected, atol=1e-4, rtol=0)
    # elsewhere the covered pixels move almost the same way: perspective changes the projected
    # covariance a little between the two positions (A = sqrt(S_b) sqrt(S_a)^-1 is not exactly I)
    assert (flow[valid] - expected).abs().max() < 0.03 * expected.norm()


def test_scaled_gaussian_flow_follows_the_affine_map():
    K, mean, quats, scales, opacity = _one_gaussian()
    scales_b = scales * torch.tensor([[1.6, 0.7, 1.0]])
    flow, valid, pa, pb, _, _ = _render_flow(mean, mean, quats, scales, scales_b, opacity, torch.eye(4), torch.eye(4), K)
    q = pixel_grid(H, W, flow)
    A = torch.diag(torch.sqrt(pb.cov2d[0].diagonal() / pa.cov2d[0].diagonal()))  # axis-aligned: diagonal roots
    expected = (q - pa.means2d[0]) @ A.T + pb.means2d[0] - q
    assert valid.sum() > 20
    torch.testing.assert_close(flow[valid], expected[valid], atol=1e-3, rtol=0)
    assert flow[10, 16, 0] > 0.5  # pixels right of the centre move right as the Gaussian widens


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_blended_flow_equals_the_dense_twin(backend):
    scene = random_scene(14, W, H, seed=3, pixel_sigma=(1.5, 5.0), opacity=(0.3, 0.9))
    g = torch.Generator().manual_seed(1)
    means_b = scene.means + 0.15 * torch.randn(scene.means.shape, generator=g)
    scales_b = scene.scales * torch.exp(0.3 * torch.randn(scene.scales.shape, generator=g))
    centre_a, rotation_a = -scene.viewmat[:3, :3].T @ scene.viewmat[:3, 3], scene.viewmat[:3, :3].T
    viewmat_b = look_from(centre_a + torch.tensor([0.05, 0.02, -0.03]), rotation_a @ _rot_y(2.0))
    flow, valid, pa, pb, _, alpha = _render_flow(scene.means, means_b, scene.quats, scene.scales, scales_b,
                                                 scene.opacities, scene.viewmat, viewmat_b, scene.K, backend=backend)
    identity = torch.eye(14)
    weights, _, _ = composite(pa, scene.opacities, identity, W, H, backend="reference")
    dense = full_flow_dense(weights, pa, pb)
    assert valid.sum() > 50
    torch.testing.assert_close(flow[valid], dense[valid], atol=2e-3, rtol=1e-4)


def _rot_y(degrees: float, dtype=torch.float32) -> torch.Tensor:
    a = math.radians(degrees)
    return torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]], dtype=dtype)


def _plane(count=24, z=4.0, dtype=torch.float32):
    """A fronto-parallel carpet of small Gaussians covering the view of an identity camera."""
    K = intrinsics(W, H, focal=20.0, dtype=dtype)
    u, v = torch.meshgrid(torch.linspace(-6, W + 6, count), torch.linspace(-6, H + 6, count), indexing="xy")
    means = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, torch.full_like(u, z)], -1)
    means = means.reshape(-1, 3).to(dtype)
    n = means.shape[0]
    scales = torch.tensor([[0.35, 0.35, 0.01]], dtype=dtype).repeat(n, 1)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype).repeat(n, 1)
    return K, means, quats, scales, torch.full((n,), 0.95, dtype=dtype)


@pytest.mark.parametrize("motion", ["translation", "rotation"])
def test_camera_motion_over_a_static_model_full_flow_equals_camera_flow(motion):
    K, means, quats, scales, opac = _plane()
    position = torch.tensor([0.25, -0.1, 0.0]) if motion == "translation" else torch.zeros(3)
    viewmat_b = look_from(position, _rot_y(0.0 if motion == "translation" else 1.5))
    flow, valid, _, _, depth, alpha = _render_flow(means, means, quats, scales, scales, opac, torch.eye(4), viewmat_b, K)
    cam, cam_valid = camera_flow(depth, alpha, K, torch.eye(4), K, viewmat_b)
    both = valid & cam_valid
    assert both.float().mean() > 0.9
    tolerance = 1e-3 if motion == "translation" else 0.05  # the affine map approximates the homography
    assert (flow[both] - cam[both]).abs().max() < tolerance
    assert cam[both].abs().max() > 0.3  # the cameras really moved


def test_identical_frames_give_zero_flow():
    scene = random_scene(10, W, H, seed=5)
    flow, valid, _, _, depth, alpha = _render_flow(scene.means, scene.means, scene.quats, scene.scales, scene.scales,
                                                   scene.opacities, scene.viewmat, scene.viewmat, scene.K, min_alpha=0.2)
    assert valid.any()
    assert flow.abs().max() < 1e-3
    cam, cam_valid = camera_flow(depth, alpha, scene.K, scene.viewmat, scene.K, scene.viewmat, 0.2)
    assert cam_valid.any() and cam.abs().max() < 1e-3


def test_gradcheck_of_the_flow_channels():
    dtype = torch.float64
    K, mean, quats, scales, opacity = _one_gaussian(dtype)
    means_a = torch.cat([mean, mean + torch.tensor([[0.5, 0.3, 0.4]], dtype=dtype)])
    quats2 = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.9, 0.1, 0.3, 0.2]], dtype=dtype)
    scales_a = torch.tensor([[0.8, 0.6, 0.5], [0.5, 0.9, 0.4]], dtype=dtype)
    opac = torch.tensor([0.7, 0.6], dtype=dtype)
    weights = torch.randn(H, W, 2, generator=torch.Generator().manual_seed(0), dtype=dtype)

    def loss(m_a, m_b, s_a, s_b):
        flow, _, _, _, _, _ = _render_flow(m_a, m_b, quats2, s_a, s_b, opac, torch.eye(4, dtype=dtype),
                                           torch.eye(4, dtype=dtype), K, min_alpha=0.05)
        return (flow * weights).sum()

    inputs = (means_a.clone().requires_grad_(), (means_a + 0.2).clone().requires_grad_(),
              scales_a.clone().requires_grad_(), (scales_a * 1.2).clone().requires_grad_())
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradcheck_of_camera_flow():
    dtype = torch.float64
    g = torch.Generator().manual_seed(2)
    depth = (2.0 + torch.rand(6, 7, 1, generator=g, dtype=dtype)).requires_grad_()
    alpha = torch.ones(6, 7, 1, dtype=dtype)
    K = intrinsics(7, 6, focal=8.0, dtype=dtype)
    viewmat_b = look_from(torch.tensor([0.2, 0.1, -0.1], dtype=dtype), _rot_y(3.0, dtype))
    weights = torch.randn(6, 7, 2, generator=g, dtype=dtype)
    assert torch.autograd.gradcheck(
        lambda d: (camera_flow(d, alpha, K, torch.eye(4, dtype=dtype), K, viewmat_b)[0] * weights).sum(), (depth,))


def _finite_grads(*tensors):
    return all(t.grad is None or torch.isfinite(t.grad).all() for t in tensors)


@pytest.mark.parametrize("case", ["transparent", "behind_camera_b", "far_outside", "needle", "same_frame"])
def test_hard_cases_are_finite(case):
    K, mean, quats, scales, opacity = _one_gaussian()
    means_a = mean.clone()
    means_b = mean.clone()
    scales_a, scales_b = scales.clone(), scales.clone()
    if case == "transparent":
        opacity = torch.tensor([1e-4])
    elif case == "behind_camera_b":
        means_b = mean * torch.tensor([[1.0, 1.0, -1.0]])
    elif case == "far_outside":
        means_b = mean + torch.tensor([[400.0, -300.0, 0.0]])
    elif case == "needle":
        scales_a = torch.tensor([[1e-8, 2.0, 1e-8]])
        scales_b = torch.tensor([[2.0, 1e-8, 1e-8]])
    leaves = [t.requires_grad_() for t in (means_a, means_b, scales_a, scales_b)]
    flow, valid, pa, pb, depth, alpha = _render_flow(*leaves[:2], quats, leaves[2], leaves[3], opacity,
                                                     torch.eye(4), torch.eye(4), K)
    assert torch.isfinite(flow).all()
    image_a = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0))
    image_b = image_a.roll(1, dims=1)
    warped, inside = backward_warp(image_b, flow)
    loss = photometric_loss(warped, image_a, valid & inside)
    cam, cam_valid = camera_flow(depth, alpha, K, torch.eye(4), K, torch.eye(4))
    loss = loss + photometric_loss(backward_warp(image_b, cam)[0], image_a, cam_valid)
    assert torch.isfinite(loss)
    loss.backward()
    assert _finite_grads(*leaves)
    if case == "transparent":
        assert not valid.any()
    if case == "behind_camera_b":
        assert not valid.any()  # the target of every covered pixel is undefined
    if case == "far_outside":
        assert valid.any() and not (valid & inside).any()


def test_camera_flow_invalid_depths():
    K = intrinsics(6, 5, focal=6.0)
    depth = torch.tensor([0.0, -1.0, float("nan"), float("inf"), 2.0]).repeat(5, 6)[:5, :6].unsqueeze(-1)
    depth = depth.clone().requires_grad_()
    viewmat_b = look_from(torch.tensor([0.0, 0.0, 3.0]), torch.eye(3))  # camera b in front of the points
    flow, valid = camera_flow(depth, torch.ones(5, 6, 1), K, torch.eye(4), K, viewmat_b)
    assert torch.isfinite(flow).all()
    bad = ~torch.isfinite(depth.detach()[..., 0]) | (depth.detach()[..., 0] <= 0)
    assert not valid[bad].any()
    flow.sum().backward()
    assert torch.isfinite(depth.grad).all()


def test_backward_warp_shifts_and_masks():
    image = torch.arange(H * W, dtype=torch.float32).reshape(H, W, 1)
    flow = torch.zeros(H, W, 2)
    flow[..., 0] = 2.0  # sample two pixels to the right
    warped, inside = backward_warp(image, flow)
    torch.testing.assert_close(warped[:, :-2], image[:, 2:])
    assert inside[:, :-2].all() and not inside[:, -1].any()
    half = torch.full((H, W, 2), 0.5)
    warped, _ = backward_warp(image, half)
    torch.testing.assert_close(warped[3, 4, 0], (image[3, 4, 0] + image[3, 5, 0] + image[4, 4, 0] + image[4, 5, 0]) / 4)


def test_photometric_loss_ignores_masked_pixels():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(H, W, 3, generator=g)
    pred = target.clone().requires_grad_()
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[:, :5] = False
    garbage = pred.detach().clone()
    garbage[:, :5] = 1e6
    loss = photometric_loss(torch.where(mask[..., None], pred, garbage), target, mask)
    assert float(loss.detach()) < 1e-6  # the masked garbage neither counts nor leaks through SSIM's window
    off = photometric_loss(pred + 0.1, target, mask)
    assert 0.07 < float(off.detach()) < 0.2
    empty = photometric_loss(pred, target, torch.zeros(H, W, dtype=torch.bool))
    empty.backward()
    assert float(empty.detach()) == 0.0 and torch.isfinite(pred.grad).all()


def test_gaussian_blur_preserves_constants_and_mass():
    image = torch.full((9, 11, 2), 0.25)
    torch.testing.assert_close(gaussian_blur(image, 1.5), image)
    spike = torch.zeros(15, 15, 1)
    spike[7, 7] = 1.0
    blurred = gaussian_blur(spike, 1.0)
    assert abs(float(blurred.sum()) - 1.0) < 1e-5 and blurred[7, 7, 0] < 0.2


def test_occlusion_mask():
    fwd = torch.zeros(H, W, 2)
    fwd[..., 0] = 1.0
    bwd = -fwd.clone()
    assert occlusion_mask(fwd, bwd)[:, :-2].all()
    bwd[5:8, 5:10] = 4.0
    ok = occlusion_mask(fwd, bwd)
    assert not ok[6, 6] and ok[0, 0]


def test_flow_channels_stay_finite_for_a_gaussian_blown_up_in_view_b():
    """The case that stopped a real NVIDIA run twice (NaN channels, then non-finite gradients): a
    Gaussian small in view a (cov ~1 px^2) whose deformed scale exploded at t_b (cov ~1e21 px^2,
    culled there). It is no flow target: marked invalid, channels finite, its gradients zero; a
    normal Gaussian beside it keeps its target and its gradient."""
    from baselines.render import Projection

    def projection(means2d, covs, depths):
        cov2d = torch.tensor(covs, requires_grad=True)
        c = cov2d.detach().double()
        det = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] ** 2
        conics = torch.stack([c[:, 1, 1] / det, -c[:, 0, 1] / det, c[:, 0, 0] / det], -1).float()
        return Projection(means2d=torch.tensor(means2d, requires_grad=True), cov2d=cov2d, conics=conics,
                          depths=torch.tensor(depths), radii=torch.zeros(2, 2, dtype=torch.int32),
                          visible=torch.tensor([False, True])), cov2d
    normal = [[2.0, 0.3], [0.3, 1.5]]
    pa, _ = projection([[142.1, 53.9], [40.0, 30.0]], [[[0.897, 0.429], [0.429, 0.610]], normal], [34.6, 30.0])
    pb, cov_b = projection([[171.9, 14.8], [42.0, 31.0]], [[[1.682e21, -1.516e20], [-1.516e20, 1.367e19]], normal],
                           [36.0, 30.0])
    assert not torch.isfinite(cov_b[0, 0, 0] * cov_b[0, 1, 1])    # its raw det overflows float32
    features = flow_features(pa, pb)
    assert torch.isfinite(features).all()
    assert features[:, 6].tolist() == [0.0, 1.0]                  # no target for the blown-up one
    torch.testing.assert_close(features[1, 4:6], torch.tensor([2.0, 1.0]), atol=1e-4, rtol=0)  # same cov: a shift
    features.sum().backward()
    for grad in (cov_b.grad, pa.means2d.grad, pb.means2d.grad):   # (a's conic is built detached)
        assert torch.isfinite(grad).all() and (grad[0] == 0).all()
    assert pb.means2d.grad[1].abs().sum() > 0
    # and the trace-scaled square root is still a root at that magnitude
    a, b, c = sqrtm_spd2(cov_b[0, 0, 0].detach().double(), cov_b[0, 0, 1].detach().double(),
                         cov_b[0, 1, 1].detach().double())
    root = torch.stack([a, b, b, c]).reshape(2, 2)
    torch.testing.assert_close(root @ root, cov_b[0].detach().double(), rtol=1e-6, atol=1e13)


def test_cached_pixel_grid_made_under_inference_mode_still_trains():
    """The pixel grid is cached per size; a first call under torch.inference_mode (an evaluation
    script) must not cache a tensor that autograd later refuses to save."""
    from reflow_plugin.flow import _pixel_grid, full_flow, pixel_grid

    _pixel_grid.cache_clear()
    with torch.inference_mode():
        pixel_grid(5, 7, torch.zeros(1))
    maps = torch.zeros(5, 7, 7)
    maps[..., 0] = maps[..., 3] = maps[..., 6] = 1.0
    maps.requires_grad_(True)
    flow, valid = full_flow(maps, torch.ones(5, 7, 1))
    flow.sum().backward()
    assert valid.all() and maps.grad is not None and torch.isfinite(maps.grad).all()
