"""HexPlane field: 4DGS semantics (layout, init, lookup, normalisation, regularisers)."""

import pytest
import torch
import torch.nn.functional as F

from baselines.fourdgs import plane_kernel
from baselines.fourdgs.hexplane import HexPlaneField, sample_plane
from baselines.fourdgs.regularization import (
    hexplane_regularization,
    hexplane_regularization_reference,
    plane_smoothness,
)
from benchmarks.deformation import PlainHexPlane

# Both lookup paths: the compiled kernel (plane_kernel.py) and the torch path it falls back to
# (parametrised indirectly: ["kernel", "torch"]).
@pytest.fixture
def lookup_engine(request, monkeypatch):
    engine = request.param
    monkeypatch.setenv(plane_kernel.ENV_SWITCH, "1" if engine == "kernel" else "0")
    if engine == "kernel":
        ok, reason = plane_kernel.LIBRARY.available()
        if not ok:
            pytest.skip(reason)
    return engine


CONFIG = {"grid_dimensions": 2, "input_coordinate_dim": 4, "output_coordinate_dim": 3, "resolution": [4, 5, 6, 3]}


def test_plane_shapes_follow_4dgs_layout():
    field = HexPlaneField(1.6, CONFIG, [1, 2])
    # pair (a, b) -> [1, C, res[b], res[a]]; spatial resolutions scaled per level, time not.
    expected = {
        0: [(1, 3, 5, 4), (1, 3, 6, 4), (1, 3, 3, 4), (1, 3, 6, 5), (1, 3, 3, 5), (1, 3, 3, 6)],
        1: [(1, 3, 10, 8), (1, 3, 12, 8), (1, 3, 3, 8), (1, 3, 12, 10), (1, 3, 3, 10), (1, 3, 3, 12)],
    }
    for level, shapes in expected.items():
        assert [tuple(p.shape) for p in field.grids[level]] == shapes
    assert field.feat_dim == 6
    assert field.aabb.requires_grad is False
    torch.testing.assert_close(field.aabb.data, torch.tensor([[1.6] * 3, [-1.6] * 3]))


def test_time_planes_start_at_one_so_time_is_neutral():
    torch.manual_seed(0)
    field = HexPlaneField(1.0, CONFIG, [1, 2])
    for level in field.grids:
        for index in (2, 4, 5):
            assert torch.equal(level[index], torch.ones_like(level[index]))
        for index in (0, 1, 3):
            assert level[index].min() >= 0.1 and level[index].max() <= 0.5
            assert level[index].std() > 0.01  # really random, not constant
    pts = torch.rand(50, 3) * 2 - 1
    early = field(pts, torch.zeros(50, 1))
    late = field(pts, torch.full((50, 1), 0.8))
    assert torch.equal(early, late)
    with torch.no_grad():
        field.grids[0][2].add_(torch.randn_like(field.grids[0][2]))
    assert not torch.allclose(field(pts, torch.zeros(50, 1)), field(pts, torch.full((50, 1), 0.8)))


def test_lookup_equals_hand_computed_bilinear_value():
    plane = torch.tensor([[[[1.0, 2.0, 4.0], [8.0, 16.0, 32.0]]]])  # [1, 1, H=2, W=3]
    u, v = torch.tensor([0.25]), torch.tensor([-0.5])
    # align_corners=True: x = (u + 1) / 2 * (W - 1) = 1.25, y = (v + 1) / 2 * (H - 1) = 0.25
    expected = 0.75 * 0.75 * 2.0 + 0.25 * 0.75 * 4.0 + 0.75 * 0.25 * 16.0 + 0.25 * 0.25 * 32.0
    assert sample_plane(plane, u, v).item() == pytest.approx(expected)
    # Border padding: outside the plane the nearest edge value is used.
    assert sample_plane(plane, torch.tensor([3.0]), torch.tensor([-7.0])).item() == pytest.approx(4.0)


def test_field_feature_is_product_of_plane_samples():
    field = HexPlaneField(1.0, {**CONFIG, "output_coordinate_dim": 1}, [1])
    with torch.no_grad():
        for plane in field.grids[0]:
            plane.fill_(1.0)
        field.grids[0][0].copy_(torch.arange(20.0).reshape(1, 1, 5, 4))  # xy plane
        field.grids[0][5].fill_(0.5)  # zt plane
    # aabb = [[1,1,1],[-1,-1,-1]]: p -> (p - 1) * 2 / (-2) - 1 = -p, so x = -1 maps to u = +1.
    point = torch.tensor([[-1.0, 1.0, 0.3]])
    value = field(point, torch.tensor([[0.2]]))
    # u = +1 -> last column (3), v = -1 -> first row (0): cell value 3.0; times 0.5 from zt.
    assert value.item() == pytest.approx(3.0 * 0.5)


@pytest.mark.parametrize("lookup_engine", ["kernel", "torch"], indirect=True)
def test_lookup_matches_grid_sample_values_and_gradients(lookup_engine):
    torch.manual_seed(0)
    # the last two have more than 4 cells per point: the index_add_ branch of the table gradient
    for height, width in [(5, 7), (1, 6), (6, 1), (25, 16), (40, 50), (1, 1300)]:
        plane = torch.rand(1, 3, height, width, dtype=torch.float64, requires_grad=True)
        edges = torch.tensor([-1.0, 1.0, 0.0, -1.0, 1.0], dtype=torch.float64)
        u = torch.cat([torch.rand(300, dtype=torch.float64) * 2.4 - 1.2, edges]).requires_grad_()
        v = torch.cat([torch.rand(300, dtype=torch.float64) * 2.4 - 1.2, edges.flip(0)]).requires_grad_()
        weights = torch.randn(305, 3, dtype=torch.float64)
        grid = torch.stack([u, v], -1).view(1, 1, -1, 2)
        reference = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True)
        reference = reference.view(3, -1).t()
        ref_grads = torch.autograd.grad((reference * weights).sum(), [plane, u, v])
        ours = sample_plane(plane, u, v)
        our_grads = torch.autograd.grad((ours * weights).sum(), [plane, u, v])
        torch.testing.assert_close(ours, reference)
        for ours_grad, ref_grad in zip(our_grads, ref_grads):
            torch.testing.assert_close(ours_grad, ref_grad)


@pytest.mark.parametrize("lookup_engine", ["kernel", "torch"], indirect=True)
def test_field_matches_4dgs_recipe_with_custom_aabb(lookup_engine):
    torch.manual_seed(1)
    field = HexPlaneField(1.6, CONFIG, [1, 2])
    plain = PlainHexPlane(1.6, CONFIG, [1, 2])
    with torch.no_grad():
        for level in field.grids:
            for plane in level:
                plane.uniform_(-1, 1)  # time planes too, so every plane matters
    field.set_aabb([2.0, 1.0, 0.5], [-1.0, -3.0, 0.0])
    plain.load_state_dict(field.state_dict())
    pts = (torch.rand(500, 3) * 4 - 2).requires_grad_()
    times = (torch.rand(500, 1) * 2.2 - 1.1).requires_grad_()  # t gradient too, beyond [-1, 1] as well
    weights = torch.randn(500, field.feat_dim)
    ours = field(pts, times)
    reference = plain(pts, times)
    torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-6)
    ours_params = [pts, times] + [p for p in field.parameters() if p.requires_grad]
    ref_params = [pts, times] + [p for p in plain.parameters() if p.requires_grad]
    ours_grads = torch.autograd.grad((ours * weights).sum(), ours_params)
    ref_grads = torch.autograd.grad((reference * weights).sum(), ref_params)
    for mine, theirs in zip(ours_grads, ref_grads):
        torch.testing.assert_close(mine, theirs, rtol=1e-4, atol=1e-5)


def test_set_aabb_uses_4dgs_orientation_and_rejects_bad_boxes():
    field = HexPlaneField(1.6, CONFIG, [1])
    field.set_aabb([2.0, 4.0, 1.0], [0.0, 0.0, -1.0])
    normalized = field.normalize(torch.tensor([[2.0, 4.0, 1.0], [0.0, 0.0, -1.0], [1.0, 2.0, 0.0]]))
    torch.testing.assert_close(normalized, torch.tensor([[-1.0] * 3, [1.0] * 3, [0.0] * 3]))
    with pytest.raises(ValueError, match="axis y"):
        field.set_aabb([1.0, 2.0, 3.0], [0.0, 2.0, 0.0])
    with pytest.raises(ValueError, match="non-finite"):
        field.set_aabb([float("nan"), 1.0, 1.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="non-finite point"):
        field(torch.tensor([[float("nan"), 0.0, 0.0]]), torch.zeros(1, 1))
    with pytest.raises(ValueError, match="non-finite timestamps"):
        field(torch.zeros(1, 3), torch.tensor([[float("inf")]]))


def test_config_errors_name_the_key():
    with pytest.raises(ValueError, match="resolution"):
        HexPlaneField(1.0, {**CONFIG, "resolution": [4, 4, 4]}, [1])
    with pytest.raises(ValueError, match="input_coordinate_dim"):
        HexPlaneField(1.0, {**CONFIG, "input_coordinate_dim": 3}, [1])
    with pytest.raises(ValueError, match="multires"):
        HexPlaneField(1.0, CONFIG, [])


def test_plane_smoothness_is_mean_squared_second_time_difference():
    rows = torch.arange(5.0)
    linear = rows.view(1, 1, 5, 1).expand(1, 2, 5, 3)
    assert plane_smoothness(linear).item() == 0.0
    quadratic = (0.5 * rows**2).view(1, 1, 5, 1).expand(1, 2, 5, 3)  # second difference = 1 everywhere
    assert plane_smoothness(quadratic).item() == pytest.approx(1.0)
    along_width = (rows**2).view(1, 1, 1, 5).expand(1, 2, 4, 5)  # varies along W only: no penalty
    assert plane_smoothness(along_width).item() == 0.0


def test_regularization_weights_apply_to_4dgs_plane_groups():
    field = HexPlaneField(1.0, {**CONFIG, "resolution": [4, 5, 6, 5]}, [1, 2])
    with torch.no_grad():
        for level in field.grids:
            for plane in level:
                plane.fill_(1.0)
        rows = torch.arange(5.0)
        field.grids[0][0].copy_((0.5 * rows**2).view(1, 1, 5, 1).expand_as(field.grids[0][0]))  # xy, spatial
        field.grids[1][4].copy_((rows**2).view(1, 1, 5, 1).expand_as(field.grids[1][4]))  # yt, time plane
    plane_tv = field.compute_regulation(0.0, 0.0, 1.0)
    time_smooth = field.compute_regulation(1.0, 0.0, 0.0)
    l1_time = field.compute_regulation(0.0, 1.0, 0.0)
    assert plane_tv.item() == pytest.approx(1.0)
    assert time_smooth.item() == pytest.approx(4.0)
    assert l1_time.item() == pytest.approx((1 - rows**2).abs().mean().item())
    total = hexplane_regularization(field.grids, 0.01, 0.001, 0.1)
    assert total.item() == pytest.approx(0.01 * 4.0 + 0.001 * l1_time.item() + 0.1 * 1.0)


@pytest.mark.parametrize("weights", [(0.01, 0.001, 0.1), (0.0, 0.3, 0.0), (0.2, 0.0, 0.0)])
def test_fused_regularization_equals_the_4dgs_formulas_with_gradients(weights):
    torch.manual_seed(3)
    # time resolution 2: the time planes are too short for a second difference (contribute 0)
    for resolution in ([4, 5, 6, 5], [4, 5, 6, 2]):
        field = HexPlaneField(1.0, {**CONFIG, "resolution": resolution}, [1, 2])
        with torch.no_grad():
            for level in field.grids:
                for plane in level:
                    plane.add_(torch.randn_like(plane))
                    plane.masked_fill_(torch.rand_like(plane) < 0.1, 1.0)  # |1 - p| at its kink
        planes = [p for level in field.grids for p in level]
        fused = hexplane_regularization(field.grids, *weights)
        fused_grads = torch.autograd.grad(fused, planes, allow_unused=True)
        reference = hexplane_regularization_reference(field.grids, *weights)
        reference_grads = torch.autograd.grad(reference, planes, allow_unused=True)
        torch.testing.assert_close(fused, reference, atol=1e-6, rtol=1e-6)
        for a, b, plane in zip(fused_grads, reference_grads, planes):
            a = torch.zeros_like(plane) if a is None else a
            b = torch.zeros_like(plane) if b is None else b
            torch.testing.assert_close(a, b, atol=1e-7, rtol=1e-5)


# ------------------------------------------------------------------ planes as views of one table
def _copy_path(field: HexPlaneField, pts: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """The lookup through a freshly built table (plane_product_lookup), the shared path's oracle."""
    from baselines.fourdgs.plane_lookup import plane_product_lookup, planes_to_table

    planes = [p for level in field.grids for p in level]
    return plane_product_lookup(planes_to_table(planes), field.layout, field.normalize(pts), times)


def _values_and_grads(field: HexPlaneField, pts, times, weights, lookup) -> tuple[torch.Tensor, list, torch.Tensor]:
    for p in field.parameters():
        p.grad = None
    pts = pts.clone().requires_grad_(True)
    out = lookup(pts, times)
    (out * weights).sum().backward()
    return out.detach(), [p.grad.clone() for level in field.grids for p in level], pts.grad


def _assert_shared_equals_copy_path(field, pts, times, weights) -> None:
    shared = _values_and_grads(field, pts, times, weights, field)
    copied = _values_and_grads(field, pts, times, weights, lambda x, t: _copy_path(field, x, t))
    torch.testing.assert_close(shared[0], copied[0], atol=1e-6, rtol=1e-6)
    for a, b in zip(shared[1], copied[1]):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(shared[2], copied[2], atol=1e-6, rtol=1e-6)


def test_planes_are_views_of_one_table_and_their_gradients_too():
    from baselines.fourdgs.plane_lookup import shared_table

    torch.manual_seed(0)
    field = HexPlaneField(1.0, CONFIG, [1, 2])
    planes = [p for level in field.grids for p in level]
    table = shared_table(planes, field.layout)
    assert table is not None and table.shape == (field.layout.num_cells, 3)
    assert all(p.untyped_storage().data_ptr() == table.untyped_storage().data_ptr() for p in planes)
    out = field(torch.rand(40, 3) * 2 - 1, torch.rand(40, 1))
    out.square().sum().backward()
    # every plane's gradient is a view of one gradient table (handed to .grad without a copy)
    assert len({p.grad.untyped_storage().data_ptr() for p in planes}) == 1
    assert all(p.grad.stride() == p.stride() for p in planes)


@pytest.mark.parametrize("lookup_engine", ["kernel", "torch"], indirect=True)
def test_shared_table_lookup_equals_the_copy_path_after_updates_and_repacking(lookup_engine):
    torch.manual_seed(1)
    field = HexPlaneField(1.0, CONFIG, [1, 2])
    with torch.no_grad():  # non-trivial time planes
        for level in field.grids:
            for p in level:
                p.add_(0.3 * torch.randn_like(p))
    pts, times, weights = torch.rand(300, 3) * 2.4 - 1.2, torch.rand(300, 1), torch.randn(300, field.feat_dim)
    _assert_shared_equals_copy_path(field, pts, times, weights)
    # an optimizer step updates the table in place: the next lookup must see the new values
    optimizer = torch.optim.Adam(field.parameters(), lr=0.05)
    field(pts, times).mul(weights).sum().backward()
    before = field(pts, times).detach()
    optimizer.step()
    after = field(pts, times).detach()
    assert (after - before).abs().max() > 1e-3
    _assert_shared_equals_copy_path(field, pts, times, weights)
    # a plane given its own storage (what module.to(device) does) is packed again, values kept
    plane = field.grids[1][3]
    plane.data = plane.data.clone()
    _assert_shared_equals_copy_path(field, pts, times, weights)
    from baselines.fourdgs.plane_lookup import shared_table

    assert shared_table([p for level in field.grids for p in level], field.layout) is not None


def test_shared_planes_keep_the_4dgs_state_dict():
    torch.manual_seed(2)
    field = HexPlaneField(1.0, CONFIG, [1, 2])
    state = field.state_dict()
    assert [tuple(v.shape) for k, v in state.items() if k.startswith("grids.1.")] == [
        (1, 3, 10, 8), (1, 3, 12, 8), (1, 3, 3, 8), (1, 3, 12, 10), (1, 3, 3, 10), (1, 3, 3, 12)]
    plain = PlainHexPlane(1.0, CONFIG, [1, 2])  # 4DGS's layer-by-layer module, contiguous planes
    plain.load_state_dict({k: v.contiguous() for k, v in state.items()})
    other = HexPlaneField(1.0, CONFIG, [1, 2])
    other.load_state_dict(plain.state_dict())
    pts, times = torch.rand(20, 3) * 2 - 1, torch.rand(20, 1)
    torch.testing.assert_close(other(pts, times), field(pts, times))
    torch.testing.assert_close(plain(pts, times), field(pts, times), atol=1e-6, rtol=1e-5)


def test_an_in_place_plane_update_between_forward_and_backward_is_an_error():
    field = HexPlaneField(1.0, CONFIG, [1, 2])
    out = field(torch.rand(10, 3) * 2 - 1, torch.rand(10, 1))
    with torch.no_grad():
        field.grids[0][0].add_(1.0)  # e.g. an optimizer step before backward
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        out.sum().backward()
