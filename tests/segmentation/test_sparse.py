"""Sparse voxel conv == dense conv3d / conv_transpose3d (forward and gradients) on small random grids."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from segmentation.sparse import (
    SparseBatchNorm,
    SparseConv3d,
    SparseReLU,
    SparseTensor,
    kernel_offsets,
    point_voxel_coords,
    point_voxel_index,
    points_to_voxels,
    sparse_cat,
    sparse_conv,
    submanifold_map,
    voxelize,
    voxels_to_points,
)

SIZE = 8  # dense grid edge (even, so stride-2 cells align with the dense grid)
ORIGIN = (-4, -8, 0)  # negative coordinates exercise the floor division; multiples of 4 align strides 2, 4


def random_sparse(generator, batch=2, channels=3, occupancy=0.3, dtype=torch.float64) -> SparseTensor:
    """Random occupied cells of a (batch, SIZE^3) grid shifted by ORIGIN, random features."""
    occupied = torch.rand(batch, SIZE, SIZE, SIZE, generator=generator) < occupancy
    idx = torch.nonzero(occupied)  # (M, 4) sorted
    coords = idx.clone()
    coords[:, 1:] += torch.tensor(ORIGIN)
    features = torch.randn(idx.shape[0], channels, generator=generator, dtype=dtype)
    return SparseTensor(features, coords, 1)


def dense_weight(weight: torch.Tensor, kernel: int, transposed: bool = False) -> torch.Tensor:
    """(K, C_in, C_out) -> conv3d (C_out, C_in, k, k, k) or conv_transpose3d (C_in, C_out, k, k, k) layout."""
    w = weight.reshape(kernel, kernel, kernel, weight.shape[1], weight.shape[2])
    return w.permute(3, 4, 0, 1, 2) if transposed else w.permute(4, 3, 0, 1, 2)


def dense_index(coords: torch.Tensor, stride: int) -> tuple[torch.Tensor, ...]:
    """Index tuple (batch, x, y, z) of sparse coords in a dense grid at `stride` starting at ORIGIN."""
    rel = (coords[:, 1:] - torch.tensor(ORIGIN)) // stride
    return coords[:, 0], rel[:, 0], rel[:, 1], rel[:, 2]


def compare(x: SparseTensor, conv: SparseConv3d, dense_fn, generator) -> None:
    """Forward and gradients (input features, weight) of the sparse conv vs the dense function."""
    features = x.features.detach().clone().requires_grad_(True)
    weight = conv.weight
    y = conv(x.replace(features))
    probe = torch.randn(y.features.shape, generator=generator, dtype=y.features.dtype)
    (y.features * probe).sum().backward()

    dense_in = x.replace(x.features.detach()).to_dense((SIZE // x.stride,) * 3, ORIGIN).requires_grad_(True)
    weight_d = weight.detach().clone().requires_grad_(True)
    dense_out = dense_fn(dense_in, weight_d)  # (B, C_out, ...)
    out_at_sites = dense_out.permute(0, 2, 3, 4, 1)[dense_index(y.coords, y.stride)]  # (M_out, C_out)
    torch.testing.assert_close(y.features, out_at_sites, rtol=1e-10, atol=1e-10)
    (out_at_sites * probe).sum().backward()
    grad_in_at_sites = dense_in.grad.permute(0, 2, 3, 4, 1)[dense_index(x.coords, x.stride)]
    torch.testing.assert_close(features.grad, grad_in_at_sites, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(weight.grad, weight_d.grad, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("keep", [False, True])
@pytest.mark.parametrize("kernel", [3, 5, 1])
def test_submanifold_equals_dense_conv3d_at_occupied_sites(generator, kernel, keep):
    x = random_sparse(generator)
    conv = SparseConv3d(3, 4, kernel_size=kernel, keep_gathers=keep).double()

    def dense(inp, w):
        return F.conv3d(inp, dense_weight(w, kernel), padding=kernel // 2)

    compare(x, conv, dense, generator)
    if kernel > 1:
        assert conv(x.replace(x.features)).coords is x.coords  # outputs = inputs


@pytest.mark.parametrize("keep", [False, True])
def test_stride2_kernel2_equals_dense_conv3d(generator, keep):
    x = random_sparse(generator)
    conv = SparseConv3d(3, 5, kernel_size=2, stride=2, keep_gathers=keep).double()
    compare(x, conv, lambda inp, w: F.conv3d(inp, dense_weight(w, 2), stride=2), generator)
    # every dense output outside the sparse output sites is exactly zero (no input there)
    y = conv(x)
    dense_out = F.conv3d(x.to_dense((SIZE,) * 3, ORIGIN), dense_weight(conv.weight.detach(), 2), stride=2)
    dense_out.permute(0, 2, 3, 4, 1)[dense_index(y.coords, 2)] = 0
    assert dense_out.abs().max() == 0
    assert y.stride == 2 and bool((y.coords[:, 1:] % 2 == 0).all())


@pytest.mark.parametrize("keep", [False, True])
def test_stride2_kernel3_equals_dense_conv3d(generator, keep):
    x = random_sparse(generator)
    conv = SparseConv3d(3, 4, kernel_size=3, stride=2, keep_gathers=keep).double()
    compare(x, conv, lambda inp, w: F.conv3d(inp, dense_weight(w, 3), stride=2, padding=1), generator)


@pytest.mark.parametrize("keep", [False, True])
def test_transposed_equals_dense_conv_transpose3d(generator, keep):
    fine = random_sparse(generator)
    down = SparseConv3d(3, 6, kernel_size=2, stride=2).double()
    coarse = down(fine)
    coarse = coarse.replace(torch.randn(coarse.features.shape, generator=generator, dtype=torch.float64))
    up = SparseConv3d(6, 4, kernel_size=2, stride=2, transposed=True, keep_gathers=keep).double()

    def dense(inp, w):
        return F.conv_transpose3d(inp, dense_weight(w, 2, transposed=True), stride=2)

    compare(coarse, up, dense, generator)
    assert up(coarse).coords is fine.coords  # back onto the stored finer voxels


def test_two_levels_down_and_up(generator):
    x = random_sparse(generator, occupancy=0.5)
    d1 = SparseConv3d(3, 4, 2, 2).double()
    d2 = SparseConv3d(4, 4, 2, 2).double()
    u2 = SparseConv3d(4, 4, 2, 2, transposed=True).double()
    y = d2(d1(x))
    assert y.stride == 4
    compare(y, u2, lambda inp, w: F.conv_transpose3d(inp, dense_weight(w, 2, True), stride=2), generator)


def test_gradcheck_custom_autograd(generator):
    x = random_sparse(generator, batch=1, channels=1, occupancy=0.1)
    kmap = submanifold_map(x)
    weight = torch.randn(27, 1, 2, generator=generator, dtype=torch.float64, requires_grad=True)
    features = x.features.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f, w: sparse_conv(f, w, kmap), (features, weight), fast_mode=True)


def test_kept_gathers_give_the_same_result_and_are_saved_only_for_backward(generator):
    x = random_sparse(generator)
    kmap = submanifold_map(x)
    with_pairs = sum(1 for i in kmap.in_idx if i is not None and i.numel())
    weight = torch.randn(27, 3, 4, generator=generator, dtype=torch.float64, requires_grad=True)
    probe = torch.randn(x.num_voxels, 4, generator=generator, dtype=torch.float64)
    results = []
    for keep in (False, True):
        features = x.features.clone().requires_grad_(True)
        y = sparse_conv(features, weight, kmap, keep_gathers=keep)
        # features + weight, plus one (P_k, C_in) gather per offset with pairs when kept
        assert len(y.grad_fn.saved_tensors) == 2 + (with_pairs if keep else 0)
        (grad_f, grad_w) = torch.autograd.grad((y * probe).sum(), (features, weight))
        results.append((y.detach(), grad_f, grad_w))
    for a, b in zip(*results):
        assert torch.equal(a, b)  # the same operations on the same values: bit-identical
    with torch.no_grad():
        assert sparse_conv(x.features, weight, kmap, keep_gathers=True).grad_fn is None
    assert torch.autograd.gradcheck(
        lambda f, w: sparse_conv(f, w, kmap, keep_gathers=True),
        (x.features.clone().requires_grad_(True), weight),
        fast_mode=True,
    )


def test_kernel_map_cached_and_shared(generator):
    x = random_sparse(generator)
    first = submanifold_map(x)
    y = SparseReLU()(x)  # replace() keeps coordinates and cache
    assert submanifold_map(y) is first
    # symmetric map: offset k and -k are the same pairs, swapped
    k = 4
    assert torch.equal(first.in_idx[k], first.out_idx[26 - k])
    assert first.in_idx[13] is None  # centre = identity
    # brute force count of neighbour pairs
    c = x.coords
    diff = c[:, None, :] - c[None, :, :]
    near = (diff[..., 0] == 0) & (diff[..., 1:].abs().max(dim=-1).values <= 1)
    assert first.num_pairs() == int(near.sum())


def test_unrelated_coordinates_get_their_own_cache(generator):
    x = random_sparse(generator)
    other = random_sparse(generator)
    z = SparseTensor(other.features, other.coords, 1, x.cache)
    assert z.cache is not x.cache


def test_voxelize_mean_and_inverse(generator):
    points = torch.rand(500, 4, generator=generator) * torch.tensor([2.0, 2.0, 1.0, 1.0]) - 1.0
    batch = torch.randint(0, 2, (500,), generator=generator)
    x, inverse = voxelize(points, 0.25, batch)
    coords = point_voxel_coords(points[:, :3], batch, 0.25)
    assert torch.equal(x.coords[inverse], coords)
    assert len(torch.unique(x.coords, dim=0)) == x.num_voxels
    for v in [0, 7, x.num_voxels - 1]:
        torch.testing.assert_close(x.features[v], points[inverse == v].mean(dim=0))
    # order of the points does not change the voxels; the list form equals the (points, batch) form
    perm = torch.randperm(500, generator=generator)
    xp, inverse_p = voxelize(points[perm], 0.25, batch[perm])
    assert torch.equal(xp.coords, x.coords) and torch.equal(inverse_p, inverse[perm])
    xl, inverse_l = voxelize([points[batch == 0], points[batch == 1]], 0.25)
    assert torch.equal(xl.coords, x.coords)
    order = torch.cat([torch.nonzero(batch == 0).squeeze(1), torch.nonzero(batch == 1).squeeze(1)])
    assert torch.equal(inverse_l, inverse[order])


def test_voxelize_rejects_bad_input():
    with pytest.raises(ValueError, match="voxel_size"):
        voxelize(torch.zeros(3, 4), 0.0)
    with pytest.raises(ValueError, match="x, y, z"):
        voxelize(torch.zeros(3, 2), 0.1)


def test_bad_conv_configs():
    with pytest.raises(ValueError):
        SparseConv3d(2, 2, kernel_size=2, stride=1)
    with pytest.raises(ValueError):
        SparseConv3d(2, 2, kernel_size=3, stride=2, transposed=True)
    with pytest.raises(ValueError):
        kernel_offsets(4)


def test_transposed_without_finer_level_fails(generator):
    x = random_sparse(generator)
    with pytest.raises(ValueError, match="finer"):
        SparseConv3d(3, 3, 2, 2, transposed=True).double()(x)


def test_trilinear_reproduces_linear_field_and_nearest():
    # a full 4x4x4 grid with feature = linear function of the voxel centre
    grid = torch.stack(torch.meshgrid(*[torch.arange(4)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)
    coords = torch.cat([torch.zeros(64, 1, dtype=torch.int64), grid], dim=1)
    centres = grid.double() + 0.5
    a = torch.tensor([[1.0, -2.0], [0.5, 3.0], [2.0, 1.0]], dtype=torch.float64)
    x = SparseTensor(centres @ a, coords, 1)
    positions = torch.tensor([[1.2, 2.7, 0.6], [2.5, 2.5, 2.5], [0.9, 3.1, 2.0]], dtype=torch.float64)
    batch = torch.zeros(3, dtype=torch.int64)
    torch.testing.assert_close(voxels_to_points(x, positions, batch), positions @ a)
    own = x.lookup(torch.cat([batch[:, None], positions.floor().long()], dim=1))
    torch.testing.assert_close(voxels_to_points(x, positions, batch, "nearest"), x.features[own])
    # gradient w.r.t. the voxel features
    features = x.features.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda f: voxels_to_points(x.replace(f), positions, batch), (features,), fast_mode=True
    )
    # a lone voxel: all other neighbours missing -> renormalised weights give its own feature
    lone = SparseTensor(torch.tensor([[5.0]], dtype=torch.float64), torch.tensor([[0, 7, 7, 7]]), 1)
    out = voxels_to_points(lone, torch.tensor([[7.05, 7.9, 7.5]], dtype=torch.float64), batch[:1])
    torch.testing.assert_close(out, torch.tensor([[5.0]], dtype=torch.float64))


def test_points_to_voxels_at_coarser_stride(generator):
    points = torch.rand(300, 4, generator=generator) * 2.0
    x, inverse = voxelize([points], 0.1)
    coarse = SparseConv3d(4, 4, 2, 2)(x)
    pc = point_voxel_coords(points[:, :3], torch.zeros(300, dtype=torch.int64), 0.1)
    assert torch.equal(point_voxel_index(x, pc), inverse)
    idx = point_voxel_index(coarse, pc)
    assert torch.equal(coarse.coords[idx][:, 1:], torch.div(pc[:, 1:], 2, rounding_mode="floor") * 2)
    pooled = points_to_voxels(points, coarse, idx)
    torch.testing.assert_close(pooled.features[idx[0]], points[idx == idx[0]].mean(dim=0))


def test_batchnorm_relu_cat_shapes(generator):
    x = random_sparse(generator, channels=4, dtype=torch.float32)
    y = SparseReLU()(SparseBatchNorm(4)(x))
    assert y.features.shape == (x.num_voxels, 4) and bool((y.features >= 0).all())
    assert sparse_cat([x, y]).features.shape == (x.num_voxels, 8)
    with pytest.raises(ValueError):
        sparse_cat([x, SparseConv3d(4, 4, 2, 2)(x)])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_matches_cpu(generator):
    x = random_sparse(generator, dtype=torch.float32)
    conv = SparseConv3d(3, 4)
    down = SparseConv3d(4, 4, 2, 2)
    up = SparseConv3d(4, 4, 2, 2, transposed=True)
    ref = up(down(conv(x))).features
    xc = SparseTensor(x.features.cuda(), x.coords.cuda())
    out = up.cuda()(down.cuda()(conv.cuda()(xc))).features
    torch.testing.assert_close(out.cpu(), ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("reach", [1, 9])  # 9 > the table margin (4 * stride): the general path
def test_shifted_lookup_equals_plain_lookup(generator, reach):
    x = random_sparse(generator)
    shifts = torch.randint(-reach, reach + 1, (6, 3), generator=generator)
    query = x.coords[None].repeat(6, 1, 1)
    query[:, :, 1:] += shifts[:, None, :]
    expected = x.lookup(query)
    assert torch.equal(x.lookup_shifted(x.coords, shifts), expected)
    hits = expected >= 0
    assert torch.equal(x.coords[expected[hits]], query[hits])
