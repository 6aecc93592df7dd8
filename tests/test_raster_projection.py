"""Projection stage: screen means, depths, 2D covariances and bounding boxes."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from baselines.render import project_gaussians, rasterize
from baselines.render.projection import ALPHA_THRESHOLD
from baselines.render.tiles import bin_gaussians
from raster_cases import camera_space_scene, project, random_scene


def _world_covariances(quats: torch.Tensor, scales: torch.Tensor) -> np.ndarray:
    """R diag(s^2) R^T with R from scipy (quaternions given w, x, y, z; scipy wants x, y, z, w)."""
    q = quats.double().numpy()
    rot = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    s2 = scales.double().numpy() ** 2
    return np.einsum("nij,nj,nkj->nik", rot, s2, rot)


def _pinhole(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    uvw = points_cam @ K.T
    return uvw[..., :2] / uvw[..., 2:3]


def test_means2d_and_depths_match_the_pinhole_model():
    scene = random_scene(200, 64, 48, seed=5, margin=0.0).to(torch.float64)
    proj = project(scene)
    viewmat = scene.viewmat.numpy()
    cam = scene.means.numpy() @ viewmat[:3, :3].T + viewmat[:3, 3]
    np.testing.assert_allclose(proj.depths.numpy(), cam[:, 2], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(proj.means2d.numpy(), _pinhole(cam, scene.K.numpy()), rtol=0, atol=1e-9)


def test_means2d_hand_values():
    # f = 10, principal point (8, 6). (0.5, -0.25, 2) -> (10 * 0.25 + 8, 10 * -0.125 + 6) = (10.5, 4.75);
    # (0, 0, 4) -> the principal point.
    scene = camera_space_scene(torch.tensor([[0.5, -0.25, 2.0], [0.0, 0.0, 4.0]]), torch.full((2, 3), 0.1),
                               torch.tensor([0.5, 0.5]), torch.ones(2, 1), width=16, height=12, focal=10.0)
    proj = project(scene)
    assert proj.means2d.tolist() == [[10.5, 4.75], [8.0, 6.0]]
    assert proj.depths.tolist() == [2.0, 4.0]


def test_cov2d_is_the_linearised_projection_plus_blur():
    # J = d(pinhole)/d(camera point) by central differences; cov2d = J Sigma_cam J^T + 0.3 I for
    # Gaussians inside the field of view (where the Jacobian clamp is inactive).
    scene = random_scene(50, 64, 48, seed=6, margin=0.0).to(torch.float64)
    proj = project(scene)
    R, t = scene.viewmat[:3, :3].numpy(), scene.viewmat[:3, 3].numpy()
    K = scene.K.numpy()
    cam = scene.means.numpy() @ R.T + t
    h = 1e-6
    jac = np.stack([(_pinhole(cam + h * e, K) - _pinhole(cam - h * e, K)) / (2 * h) for e in np.eye(3)], axis=-1)
    sigma_cam = R @ _world_covariances(scene.quats, scene.scales) @ R.T
    expected = jac @ sigma_cam @ jac.transpose(0, 2, 1) + 0.3 * np.eye(2)
    np.testing.assert_allclose(proj.cov2d.numpy(), expected, rtol=1e-6, atol=1e-8)
    # conics are the inverse covariance (a, b, c) of [[a, b], [b, c]].
    inv = np.linalg.inv(expected)
    np.testing.assert_allclose(proj.conics.numpy(), np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1),
                               rtol=1e-6, atol=1e-10)


def test_cov2d_against_monte_carlo_samples():
    # A small Gaussian (0.3% of its depth), where the linearisation is accurate: the covariance of
    # projected samples equals cov2d minus the blur.
    quats = torch.tensor([[0.9, 0.2, -0.3, 0.1]], dtype=torch.float64)
    scales = torch.tensor([[0.004, 0.01, 0.002]], dtype=torch.float64)
    mean = np.array([0.3, -0.2, 3.0])
    scene = camera_space_scene(torch.from_numpy(mean[None]), scales, torch.tensor([0.9]), torch.ones(1, 1), 64, 48,
                               focal=400.0, quats=quats, dtype=torch.float64)
    proj = project(scene)
    rng = np.random.default_rng(0)
    samples = rng.multivariate_normal(mean, _world_covariances(quats, scales)[0], size=200_000)
    empirical = np.cov(_pinhole(samples, scene.K.numpy()).T)
    np.testing.assert_allclose(empirical, proj.cov2d[0].numpy() - 0.3 * np.eye(2), rtol=0.02, atol=0.02)


def test_jacobian_clamp_beyond_1_3_times_the_half_fov():
    # f = 20, 20x20 image, principal point (10, 10): the clamp limit on x/z is
    # (20 - 10) / 20 + 0.3 * (0.5 * 20 / 20) = 0.65. A mean at x/z = 2 uses tx/z = 0.65 in J.
    s = 0.05
    scene = camera_space_scene(torch.tensor([[2.0, 0.0, 1.0]]), torch.full((1, 3), s, dtype=torch.float64), torch.tensor([0.9]),
                               torch.ones(1, 1), 20, 20, focal=20.0, dtype=torch.float64)
    proj = project(scene)
    J = np.array([[20.0, 0.0, -20.0 * 0.65], [0.0, 20.0, 0.0]])
    expected = s * s * J @ J.T + 0.3 * np.eye(2)
    np.testing.assert_allclose(proj.cov2d[0].numpy(), expected, rtol=1e-12)
    assert proj.means2d[0, 0] == 50.0  # the mean itself is not clamped


def test_near_plane_is_inclusive_like_gsplat():
    means = torch.tensor([[0.0, 0.0, 0.01], [0.0, 0.0, 0.0099]])
    scene = camera_space_scene(means, torch.full((2, 3), 0.001), torch.tensor([0.9, 0.9]), torch.ones(2, 1),
                               32, 32, focal=40.0)
    assert project(scene).visible.tolist() == [True, False]


@pytest.mark.parametrize("seed", [0, 1])
def test_bounding_boxes_and_tiles_hold_every_pixel_with_visible_alpha(seed):
    # Dense alpha o exp(-sigma) of each Gaussian alone over the whole image: wherever it reaches
    # 1/255 the pixel centre lies inside the box and the Gaussian is in that pixel's tile list;
    # culled Gaussians reach 1/255 nowhere. Low opacities exercise the opacity-aware boxes.
    width, height = 53, 41
    scene = random_scene(300, width, height, seed=seed, pixel_sigma=(0.3, 8.0), opacity=(0.0, 1.0), margin=0.4)
    low = torch.arange(300) % 3 == 0
    scene.opacities[low] = scene.opacities[low] * 0.05  # many in [0, 0.05], around the 1/255 cut
    proj = project(scene)
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    dx = xs[None] - proj.means2d[:, 0, None, None]
    dy = ys[None] - proj.means2d[:, 1, None, None]
    a, b, c = (proj.conics[:, k, None, None] for k in range(3))
    raw = scene.opacities[:, None, None] * torch.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy))
    reaches = raw >= ALPHA_THRESHOLD  # [N, H, W]
    in_front = proj.depths > 0.01
    assert not reaches[in_front & ~proj.visible].any()
    rx, ry = proj.radii[:, 0, None, None].float(), proj.radii[:, 1, None, None].float()
    inside_box = (dx.abs() <= rx) & (dy.abs() <= ry)
    assert not (reaches & ~inside_box)[proj.visible].any()
    # The boxes are not trivially huge: each is within one pixel of the 1/255 ellipse's extent.
    cov = proj.cov2d
    extend = torch.sqrt(2 * torch.log(torch.clamp(scene.opacities * 255, min=1))).clamp(max=3.33)
    for axis in (0, 1):
        half = extend * torch.sqrt(cov[:, axis, axis])
        assert torch.all(proj.radii[proj.visible, axis] <= torch.ceil(half[proj.visible]) + 1e-6)

    bins = bin_gaussians(proj, width, height)
    tile_of_pixel = (torch.arange(height)[:, None] // 16) * bins.tiles_x + torch.arange(width)[None, :] // 16
    listed = torch.zeros(300, bins.tiles_x * bins.tiles_y, dtype=torch.bool)
    for tile in range(bins.tiles_x * bins.tiles_y):
        listed[bins.gaussian_ids[bins.offsets[tile]:bins.offsets[tile + 1]], tile] = True
    assert (reaches & ~listed[:, tile_of_pixel])[proj.visible].sum() == 0
    assert proj.visible.sum() > 100 and (~proj.visible & in_front).sum() > 10  # both regimes occur


def test_project_gaussians_public_stage_matches_rasterize_meta():
    scene = random_scene(50, 40, 30, seed=9)
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K, 40, 30,
                             opacities=scene.opacities, backend="cpu")
    *_, meta = rasterize(scene.means, scene.quats, scene.scales, scene.opacities, scene.features, scene.viewmat,
                         scene.K, 40, 30, backend="cpu")
    for key in proj.keys():
        assert torch.equal(proj[key], meta[key]), key
    # and the torch twin (the cpu backend projects with the compiled kernel where it builds;
    # test_project_kernel.py holds the kernel to the twin, gradients included)
    ref = project(scene)
    for key in ("means2d", "cov2d", "conics", "depths"):
        torch.testing.assert_close(proj[key], ref[key], rtol=5e-5, atol=1e-5)
    assert torch.equal(proj.radii, ref.radii) and torch.equal(proj.visible, ref.visible)
