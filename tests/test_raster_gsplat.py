"""gsplat backend plumbing on CPU, with a stand-in `gsplat` module built from our torch stages.

The real gsplat needs CUDA, which the test machines do not have. The stand-in implements the four
stage functions with gsplat's signatures and output layouts (camera dimension, radii [C, N, 2] from
1.5 on and [C, N] before, uninitialised (here: NaN) values for culled Gaussians, float32 only,
at most 513 channels), so these tests check everything the backend does around the CUDA calls.
"""
from __future__ import annotations

import sys
import types

import pytest
import torch

from baselines.render import backends, rasterize
from baselines.render.composite_tiled import composite_bins
from baselines.render.gsplat_backend import composite_gsplat, project_gaussians_gsplat
from baselines.render.projection import Projection, project_gaussians_torch
from baselines.render.tiles import TileBins, bin_gaussians
from raster_cases import assert_grads_close, random_scene, weighted_loss


def fake_gsplat(version: str) -> types.ModuleType:
    module = types.ModuleType("gsplat")
    module.__version__ = version
    module.calls = []
    per_axis = tuple(int(v) for v in version.split(".")[:2]) >= (1, 5)

    def project(means, covars, quats, scales, viewmats, Ks, width, height, eps2d=0.3, near_plane=0.01,
                far_plane=1e10, radius_clip=0.0, packed=False, sparse_grad=False, calc_compensations=False,
                camera_model="pinhole", opacities=None):
        assert covars is None and means.dim() == 2 and viewmats.shape == (1, 4, 4) and Ks.shape == (1, 3, 3)
        assert means.dtype == torch.float32
        module.calls.append(("fully_fused_projection", opacities is not None))
        proj = project_gaussians_torch(means, quats, scales, viewmats[0], Ks[0], width, height, opacities,
                                       near_plane, far_plane, eps2d)
        vis = proj.visible
        nan = torch.tensor(float("nan"))
        means2d = torch.where(vis[:, None], proj.means2d, nan)
        conics = torch.where(vis[:, None], proj.conics, nan)
        depths = torch.where(vis, proj.depths, nan)
        radii = proj.radii if per_axis else proj.radii.amax(dim=-1)
        return radii[None], means2d[None], depths[None], conics[None], None

    if per_axis:
        def fully_fused_projection(means, covars, quats, scales, viewmats, Ks, width, height, eps2d=0.3,
                                   near_plane=0.01, far_plane=1e10, radius_clip=0.0, packed=False,
                                   sparse_grad=False, calc_compensations=False, camera_model="pinhole",
                                   opacities=None):
            return project(means, covars, quats, scales, viewmats, Ks, width, height, eps2d, near_plane,
                           far_plane, radius_clip, packed, sparse_grad, calc_compensations, camera_model, opacities)
    else:  # gsplat 1.4 has no `opacities` argument
        def fully_fused_projection(means, covars, quats, scales, viewmats, Ks, width, height, eps2d=0.3,
                                   near_plane=0.01, far_plane=1e10, radius_clip=0.0, packed=False,
                                   sparse_grad=False, calc_compensations=False, camera_model="pinhole"):
            return project(means, covars, quats, scales, viewmats, Ks, width, height, eps2d, near_plane,
                           far_plane, radius_clip, packed, sparse_grad, calc_compensations, camera_model)

    def isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, sort=True, **_):
        assert means2d.dim() == 3 and depths.dim() == 2
        assert radii.shape == (means2d.shape[:2] + (2,) if per_axis else means2d.shape[:2])
        r = radii[0] if per_axis else radii[0][:, None].expand(-1, 2)
        proj = Projection(means2d[0], None, None, depths[0], r, (r > 0).any(dim=-1))
        bins = bin_gaussians(proj, tile_width * tile_size, tile_height * tile_size, tile_size)
        counts = bins.offsets[1:] - bins.offsets[:-1]
        tile_of_isect = torch.repeat_interleave(torch.arange(counts.numel()), counts)
        isect_ids = (tile_of_isect << 32) | torch.arange(bins.num_intersections)
        flatten_ids = bins.gaussian_ids.to(torch.int32)
        return torch.bincount(bins.gaussian_ids, minlength=depths.shape[1]).int()[None], isect_ids, flatten_ids

    def isect_offset_encode(isect_ids, n_images, tile_width, tile_height):
        assert n_images == 1
        tiles = isect_ids >> 32
        offsets = torch.searchsorted(tiles, torch.arange(tile_width * tile_height))
        return offsets.to(torch.int32).reshape(1, tile_height, tile_width)

    def rasterize_to_pixels(means2d, conics, colors, opacities, image_width, image_height, tile_size,
                            isect_offsets, flatten_ids, backgrounds=None, masks=None, packed=False, absgrad=False):
        channels = colors.shape[-1]
        if channels > 513:
            raise ValueError(f"Unsupported number of color channels: {channels}")
        assert colors.dtype == torch.float32 and means2d.dim() == 3 and opacities.dim() == 2
        module.calls.append(("rasterize_to_pixels", channels))
        th, tw = isect_offsets.shape[-2:]
        offsets = torch.cat([isect_offsets.reshape(-1).long(), torch.tensor([flatten_ids.numel()])])
        bins = TileBins(tile_size, tw, th, offsets, flatten_ids.long())
        image, alpha = composite_bins(means2d[0], conics[0], opacities[0], colors[0], bins, image_width, image_height)
        return image[None], alpha[None]

    module.fully_fused_projection = fully_fused_projection
    module.isect_tiles = isect_tiles
    module.isect_offset_encode = isect_offset_encode
    module.rasterize_to_pixels = rasterize_to_pixels
    return module


@pytest.fixture(params=["1.5.3", "1.4.0"])
def gsplat_module(request, monkeypatch):
    module = fake_gsplat(request.param)
    monkeypatch.setitem(sys.modules, "gsplat", module)
    # Let the registry accept CPU tensors for this stand-in (the real check requires CUDA).
    monkeypatch.setattr(backends, "gsplat_unavailable_reason", lambda device: None)
    return module


def _render(scene, backend, background=None):
    s = scene.to(torch.float32).requires_grad_()
    image, depth, alpha, meta = rasterize(*s.args(), backend=backend, background=background)
    weighted_loss((image, depth, alpha), seed=3).backward()
    grads = {k: v.grad for k, v in s.gaussian_tensors.items()}
    return dict(image=image.detach(), depth=depth.detach(), alpha=alpha.detach(), meta=meta,
                means2d=meta.means2d.grad, **grads)


def test_public_rasterize_through_gsplat_matches_cpu(gsplat_module):
    scene = random_scene(200, 45, 37, channels=3, seed=8, pixel_sigma=(0.5, 3.0))
    background = torch.tensor([0.2, 0.3, 0.4])
    got, want = _render(scene, "gsplat", background), _render(scene, "cpu", background)
    assert got["meta"].backend == "gsplat"
    assert [c[0] for c in gsplat_module.calls] == ["fully_fused_projection", "rasterize_to_pixels"]
    for key in ("image", "alpha"):
        torch.testing.assert_close(got[key], want[key], atol=1e-5, rtol=0)
    torch.testing.assert_close(got["depth"], want["depth"], atol=1e-4, rtol=1e-5)
    for key in ("means", "quats", "scales", "opacities", "features", "means2d"):
        assert_grads_close(got[key], want[key], key)


def test_projection_replaces_culled_garbage_and_keeps_the_contract(gsplat_module):
    scene = random_scene(300, 40, 30, seed=9, margin=1.0)  # many off-screen Gaussians
    scene.means[:5, :] = scene.means[:5, :] * -1.0  # and some behind the camera
    proj = project_gaussians_gsplat(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K, 40, 30,
                                    scene.opacities)
    ref = project_gaussians_torch(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K, 40, 30,
                                  scene.opacities)
    vis = ref.visible
    assert 0 < vis.sum() < 300
    if gsplat_module.__version__ >= "1.5":
        assert torch.equal(proj.visible, vis)
    else:  # 1.4 cannot tighten boxes by opacity: a few more edge Gaussians stay (harmlessly) visible
        assert (proj.visible | ~vis).all()
        vis = proj.visible
    assert proj.radii.dtype == torch.int32 and proj.radii.shape == (300, 2)
    assert (proj.radii[~vis] == 0).all() and (proj.radii[vis] > 0).any(dim=1).all()
    for key in ("means2d", "cov2d", "conics", "depths"):
        assert torch.isfinite(proj[key]).all(), key
    assert not torch.isnan(proj.means2d).any()
    torch.testing.assert_close(proj.means2d[vis], ref.means2d[vis])
    torch.testing.assert_close(proj.conics[vis], ref.conics[vis])
    torch.testing.assert_close(proj.cov2d[vis], ref.cov2d[vis], rtol=1e-4, atol=1e-5)  # inverse of the conic
    torch.testing.assert_close(proj.depths, ref.depths)
    # culled but in front (off-screen, faint): the true projection, as the torch backend gives it
    # (flow rendering sends view a's pixels there; issue 25 item 14), not the principal point
    culled = ~vis & (ref.depths >= 0.01)
    assert culled.sum() > 20
    torch.testing.assert_close(proj.means2d[culled], ref.means2d[culled])
    torch.testing.assert_close(proj.cov2d[culled], ref.cov2d[culled])


def test_many_channels_are_split_across_calls(gsplat_module):
    scene = random_scene(60, 20, 17, channels=600, seed=10)
    proj = project_gaussians_torch(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K, 20, 17,
                                   scene.opacities)
    image, alpha = composite_gsplat(proj, scene.opacities, scene.features, 20, 17)
    assert [c[1] for c in gsplat_module.calls] == [32] * 18 + [24]
    from baselines.render.composite_tiled import composite_tiled
    want_image, want_alpha = composite_tiled(proj, scene.opacities, scene.features, 20, 17)
    torch.testing.assert_close(image, want_image, atol=1e-5, rtol=0)
    torch.testing.assert_close(alpha, want_alpha, atol=1e-5, rtol=0)


def test_zero_gaussians_never_reach_gsplat(gsplat_module):
    # gsplat's kernels crash on an empty model (seen on an H200): the backend draws nothing itself
    scene = random_scene(0, 20, 17, seed=0).requires_grad_()
    background = torch.tensor([0.2, 0.3, 0.4])
    image, depth, alpha, meta = rasterize(*scene.args(), backend="gsplat", background=background)
    assert meta.backend == "gsplat" and gsplat_module.calls == []
    assert image.shape == (17, 20, 3) and torch.equal(image, background.expand(17, 20, 3))
    assert torch.equal(alpha, torch.zeros(17, 20, 1)) and torch.isfinite(depth).all()
    weighted_loss((image, depth, alpha)).backward()  # still part of the graph: a training step does not break


def test_float64_is_rejected_with_a_clear_error(gsplat_module):
    scene = random_scene(10, 20, 17, seed=0).to(torch.float64)
    with pytest.raises(ValueError, match="float32"):
        rasterize(*scene.args(), backend="gsplat")


def test_unavailable_reasons_without_cuda():
    assert "CUDA" in backends.gsplat_unavailable_reason(torch.device("cpu"))
    if not torch.cuda.is_available():
        assert "is_available" in backends.gsplat_unavailable_reason(torch.device("cuda"))
    scene = random_scene(10, 20, 17, seed=0)
    assert rasterize(*scene.args(), backend="auto")[3].backend == "cpu"
