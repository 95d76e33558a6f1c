"""Voxel convolution on occupied voxels in plain PyTorch (no MinkowskiEngine / spconv / torchsparse).

Follows the coordinate conventions of MinkowskiEngine (Choy et al., CVPR 2019) and torchsparse (Tang et al.,
MLSys 2022): coordinates are integer voxel indices of the finest grid, `[batch, x, y, z]`; a tensor at stride
`s` holds coordinates that are multiples of `s`, and a voxel at `c` covers the cells `[c, c + s)`.

Kernel maps are built by hashing coordinates to int64 keys (mixed radix over the occupied extent), sorting the
keys once per stride and looking queries up with `torch.searchsorted`. A convolution is gather-GEMM-scatter
per kernel offset (`index_select`, `mm`, `index_add_`) with weights `(K, C_in, C_out)`; a custom autograd
function either recomputes the gathers in backward, so that only the input features are kept for it, or keeps
the forward's gathers (`keep_gathers`: more memory, one gather fewer per offset).

Every operation works on CPU and CUDA tensors alike. Dense equivalents (checked in tests/segmentation/test_sparse.py):
- submanifold conv, odd kernel k      == conv3d(kernel k, padding k // 2) read at the input sites
- downsampling conv, kernel 2 stride 2 == conv3d(kernel 2, stride 2) read at the occupied output sites
- downsampling conv, kernel 3 stride 2 == conv3d(kernel 3, stride 2, padding 1) read at the same sites
- transposed conv, kernel 2 stride 2   == conv_transpose3d(kernel 2, stride 2) read at the stored finer sites
with the dense weight `w.reshape(k, k, k, C_in, C_out).permute(4, 3, 0, 1, 2)` (x, y, z = D, H, W axes).
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

# --------------------------------------------------------------------------------------- hashing


@dataclass
class _KeyTable:
    """Sorted int64 keys of one coordinate set; `lo`/`extent` define the mixed radix of the keys."""

    lo: torch.Tensor  # (4,) int64, smallest coordinate per column
    extent: torch.Tensor  # (4,) int64, number of values per column
    sorted_keys: torch.Tensor  # (M,) int64
    order: torch.Tensor  # (M,) int64, sorted_keys = keys[order]


@dataclass(eq=False)
class KernelMap:
    """Pairs of one convolution: for kernel offset k, out[out_idx[k]] += in[in_idx[k]] @ W[k].

    An offset whose map is the identity (the centre of a submanifold conv) stores `None` in both lists so
    that the convolution skips its gather and scatter.
    """

    in_idx: list[torch.Tensor | None]
    out_idx: list[torch.Tensor | None]
    num_in: int
    num_out: int

    def transposed(self) -> KernelMap:
        """The same pairs with input and output swapped (kernel-2 downsampling -> its transposed conv)."""
        return KernelMap(list(self.out_idx), list(self.in_idx), self.num_out, self.num_in)

    def num_pairs(self) -> int:
        """Total number of (input, output) pairs over all offsets."""
        return sum(self.num_in if i is None else int(i.numel()) for i in self.in_idx)


@dataclass(eq=False)
class CoordCache:
    """Coordinates per stride and the kernel maps built on them, shared by all tensors of one voxelization."""

    coords: dict[int, torch.Tensor] = field(default_factory=dict)
    tables: dict[int, _KeyTable] = field(default_factory=dict)
    kernel_maps: dict[tuple, KernelMap] = field(default_factory=dict)
    point_index: dict[int, torch.Tensor] = field(default_factory=dict)  # stride -> (N,) voxel of each point
    interpolation: dict[tuple, tuple] = field(default_factory=dict)  # (stride, mode) -> (positions, batch, CSR)


def _make_table(coords: torch.Tensor, margin: int = 0) -> _KeyTable:
    """Key table whose box extends `margin` beyond the coordinates in x, y, z (room for kernel offsets)."""
    pad = torch.tensor([0, margin, margin, margin], device=coords.device)
    lo = (coords.min(dim=0).values if coords.shape[0] else coords.new_zeros(4)) - pad
    hi = (coords.max(dim=0).values if coords.shape[0] else coords.new_zeros(4)) + pad
    extent = hi - lo + 1
    if math.prod(int(e) for e in extent.tolist()) >= 2**62:
        raise ValueError(f"coordinate extent {extent.tolist()} too large to hash into int64 keys")
    keys = _hash(coords, lo, extent)
    sorted_keys, order = torch.sort(keys)
    return _KeyTable(lo, extent, sorted_keys, order)


def _hash(coords: torch.Tensor, lo: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
    """(..., 4) int64 coordinates inside the table's box -> (...,) int64 mixed-radix keys."""
    c = coords - lo
    return ((c[..., 0] * extent[1] + c[..., 1]) * extent[2] + c[..., 2]) * extent[3] + c[..., 3]


def _find(table: _KeyTable, keys: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Keys (any shape) -> row index into the table's coordinates, -1 where absent or not `valid`."""
    if table.sorted_keys.numel() == 0:
        return torch.full_like(keys, -1)
    pos = torch.searchsorted(table.sorted_keys, keys.reshape(-1)).reshape(keys.shape)
    pos = pos.clamp_max(table.sorted_keys.numel() - 1)
    found = table.sorted_keys[pos] == keys
    if valid is not None:
        found &= valid
    return torch.where(found, table.order[pos], torch.full_like(pos, -1))


def _lookup(table: _KeyTable, query: torch.Tensor) -> torch.Tensor:
    """(..., 4) query coordinates -> (...,) row index into the table's coordinates, -1 where absent."""
    rel = query - table.lo
    inside = ((rel >= 0) & (rel < table.extent)).all(dim=-1)
    return _find(table, _hash(query, table.lo, table.extent).masked_fill(~inside, -1), inside)


def _lookup_shifted(table: _KeyTable, base: torch.Tensor, shifts: torch.Tensor) -> torch.Tensor:
    """(M, 4) coordinates + (K, 3) spatial shifts -> (K, M) row of base + shift, -1 where absent.

    When every shifted coordinate stays inside the table's box (the usual case, the box has a margin), the
    keys are the base keys plus one constant per shift, so only M coordinates are hashed.
    """
    if base.shape[0] == 0:
        return base.new_full((shifts.shape[0], 0), -1)
    lo_q = base.min(dim=0).values
    hi_q = base.max(dim=0).values
    lo_q[1:] += shifts.min(dim=0).values
    hi_q[1:] += shifts.max(dim=0).values
    if bool((lo_q >= table.lo).all() and (hi_q < table.lo + table.extent).all()):
        e = table.extent
        radix = torch.stack([e[2] * e[3], e[3], torch.ones_like(e[3])])  # key step per unit of x, y, z
        keys = _hash(base, table.lo, table.extent)[None] + (shifts * radix).sum(dim=1)[:, None]  # (K, M)
        return _find(table, keys)
    query = base[None].repeat(shifts.shape[0], 1, 1)
    query[:, :, 1:] += shifts[:, None, :]
    return _lookup(table, query)


def kernel_offsets(kernel_size: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(K, 3) int64 offsets in x-major order: {-k//2..k//2}^3 for odd k, {0, 1}^3 for k = 2."""
    if kernel_size == 2:
        values = range(2)
    elif kernel_size % 2 == 1 and kernel_size > 0:
        values = range(-(kernel_size // 2), kernel_size // 2 + 1)
    else:
        raise ValueError(f"kernel_size must be odd or 2, got {kernel_size}")
    return torch.tensor(list(itertools.product(values, repeat=3)), dtype=torch.int64, device=device)


def _floor_to(coords: torch.Tensor, step: int) -> torch.Tensor:
    """Spatial columns rounded down to multiples of `step` (floor, also for negative coordinates)."""
    out = coords.clone()
    out[:, 1:] = torch.div(coords[:, 1:], step, rounding_mode="floor") * step
    return out


# ----------------------------------------------------------------------------------- sparse tensor


@dataclass(eq=False)
class SparseTensor:
    """Features on occupied voxels: features (M, C), coords (M, 4) int64 [batch, x, y, z], stride s."""

    features: torch.Tensor  # (M, C)
    coords: torch.Tensor  # (M, 4) int64, spatial columns multiples of `stride`
    stride: int = 1
    cache: CoordCache = field(default_factory=CoordCache)

    def __post_init__(self) -> None:
        if self.coords.ndim != 2 or self.coords.shape[1] != 4:
            raise ValueError(f"coords must be (M, 4) [batch, x, y, z], got {tuple(self.coords.shape)}")
        if self.features.ndim != 2 or self.features.shape[0] != self.coords.shape[0]:
            raise ValueError(
                f"features must be (M, C) with M = {self.coords.shape[0]}, got {tuple(self.features.shape)}"
            )
        if self.coords.dtype != torch.int64:
            self.coords = self.coords.long()
        known = self.cache.coords.get(self.stride)
        if known is None:
            self.cache.coords[self.stride] = self.coords
        elif known is not self.coords:  # other coordinates: the cached maps do not apply to them
            self.cache = CoordCache(coords={self.stride: self.coords})

    def replace(self, features: torch.Tensor) -> SparseTensor:
        """Same coordinates, stride and cache with new features (M, C')."""
        return SparseTensor(features, self.coords, self.stride, self.cache)

    @property
    def num_voxels(self) -> int:
        return int(self.coords.shape[0])

    def table(self, stride: int | None = None) -> _KeyTable:
        """Sorted key table of the coordinates at `stride` (default: this tensor's), built once."""
        stride = self.stride if stride is None else stride
        table = self.cache.tables.get(stride)
        if table is None:
            table = _make_table(self.cache.coords[stride], margin=4 * stride)
            self.cache.tables[stride] = table
        return table

    def lookup(self, query: torch.Tensor, stride: int | None = None) -> torch.Tensor:
        """(..., 4) coordinates -> (...,) row of that voxel at `stride` (default: own), -1 if absent."""
        return _lookup(self.table(stride), query)

    def lookup_shifted(self, base: torch.Tensor, shifts: torch.Tensor, stride: int | None = None) -> torch.Tensor:
        """(M, 4) coords + (K, 3) shifts -> (K, M) row of each shifted voxel at `stride`, -1 if absent."""
        return _lookup_shifted(self.table(stride), base, shifts)

    def to_dense(self, shape: Sequence[int], origin: Sequence[int] = (0, 0, 0)) -> torch.Tensor:
        """(B, C, X, Y, Z) zero-filled grid; cell (i, j, k) holds voxel origin + stride * (i, j, k)."""
        b = int(self.coords[:, 0].max()) + 1 if self.num_voxels else 1
        dense = self.features.new_zeros(b, self.features.shape[1], *shape)
        idx = (self.coords[:, 1:] - torch.as_tensor(origin, device=self.coords.device)) // self.stride
        dense[self.coords[:, 0], :, idx[:, 0], idx[:, 1], idx[:, 2]] = self.features
        return dense


def sparse_cat(tensors: Sequence[SparseTensor]) -> SparseTensor:
    """Concatenate features of tensors that share coordinates (U-Net skip connections)."""
    first = tensors[0]
    for t in tensors[1:]:
        if t.stride != first.stride or not (t.coords is first.coords or torch.equal(t.coords, first.coords)):
            raise ValueError("sparse_cat needs tensors on the same coordinates")
    return first.replace(torch.cat([t.features for t in tensors], dim=1))


# -------------------------------------------------------------------------------------- voxelize


def voxelize(
    points: torch.Tensor | Sequence[torch.Tensor],
    voxel_size: float,
    batch_index: torch.Tensor | None = None,
    features: torch.Tensor | None = None,
) -> tuple[SparseTensor, torch.Tensor]:
    """Points -> (SparseTensor of mean-pooled point features at stride 1, inverse (N,) point -> voxel).

    `points` is a list of (N_b, D) scans or one (N, D) tensor with `batch_index` (N,); columns 0-2 are x, y, z
    in metres. The voxel features are the per-voxel mean of `features` (N, C) if given, else of all D columns.
    Voxel coordinates are floor(xyz / voxel_size); voxels come out sorted by (batch, x, y, z), so they do not
    depend on the order of the points.
    """
    if isinstance(points, torch.Tensor):
        if batch_index is None:
            batch_index = torch.zeros(points.shape[0], dtype=torch.int64, device=points.device)
    else:
        if len(points) == 0:
            raise ValueError("voxelize needs at least one scan")
        batch_index = torch.cat(
            [torch.full((p.shape[0],), b, dtype=torch.int64, device=p.device) for b, p in enumerate(points)]
        )
        points = torch.cat(list(points), dim=0)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be (N, D >= 3) with x, y, z first, got {tuple(points.shape)}")
    if batch_index.shape != (points.shape[0],):
        raise ValueError(f"batch_index must be ({points.shape[0]},), got {tuple(batch_index.shape)}")
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    point_coords = point_voxel_coords(points[:, :3], batch_index, voxel_size)  # (N, 4)
    table = _make_table(point_coords)
    unique_keys, inverse = torch.unique(_hash(point_coords, table.lo, table.extent), return_inverse=True)
    num = unique_keys.numel()
    coords = point_coords.new_empty(num, 4)
    coords[inverse] = point_coords
    if features is None:
        features = points
    elif features.shape[0] != points.shape[0]:
        raise ValueError(f"features must have one row per point ({points.shape[0]}), got {features.shape[0]}")
    tensor = SparseTensor(scatter_mean(features, inverse, num), coords, 1)
    tensor.cache.point_index[1] = inverse
    return tensor, inverse


def point_voxel_coords(xyz: torch.Tensor, batch_index: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """(N, 3) metres + (N,) batch -> (N, 4) int64 [batch, floor(x / voxel_size), ...]."""
    grid = torch.floor(xyz / voxel_size).long()
    return torch.cat([batch_index.long()[:, None], grid], dim=1)


def scatter_mean(values: torch.Tensor, index: torch.Tensor, num: int) -> torch.Tensor:
    """(N, C) values averaged into `num` rows by (N,) index (rows without values stay 0)."""
    total = values.new_zeros(num, values.shape[1]).index_add_(0, index, values)
    count = torch.bincount(index, minlength=num).clamp_min(1).to(values.dtype)
    return total / count[:, None]


# ----------------------------------------------------------------------------------- kernel maps


def submanifold_map(x: SparseTensor, kernel_size: int = 3) -> KernelMap:
    """Kernel map of a submanifold conv (outputs = inputs); offsets k and -k share one lookup (symmetry)."""
    key = ("sub", x.stride, kernel_size)
    kmap = x.cache.kernel_maps.get(key)
    if kmap is not None:
        return kmap
    offsets = kernel_offsets(kernel_size, x.coords.device) * x.stride  # (K, 3)
    num_k, centre = offsets.shape[0], offsets.shape[0] // 2
    in_idx: list[torch.Tensor | None] = [None] * num_k
    out_idx: list[torch.Tensor | None] = [None] * num_k
    half = torch.arange(centre, device=x.coords.device)  # offsets before the centre; k' = K-1-k is -offset
    found = x.lookup_shifted(x.coords, offsets[half])  # (K/2, M): input at out + offset
    for k in range(centre):
        out_rows = torch.nonzero(found[k] >= 0).squeeze(1)
        in_rows = found[k][out_rows]
        in_idx[k], out_idx[k] = in_rows, out_rows
        in_idx[num_k - 1 - k], out_idx[num_k - 1 - k] = out_rows, in_rows  # out + (-offset) = in
    kmap = KernelMap(in_idx, out_idx, x.num_voxels, x.num_voxels)
    x.cache.kernel_maps[key] = kmap
    return kmap


def downsample_coords(x: SparseTensor) -> torch.Tensor:
    """Coordinates at stride 2s (floor of the occupied stride-s voxels), cached."""
    out_stride = 2 * x.stride
    coords = x.cache.coords.get(out_stride)
    if coords is None:
        _stride2_map(x)
        coords = x.cache.coords[out_stride]
    return coords


def _stride2_map(x: SparseTensor) -> KernelMap:
    """Kernel map of the kernel-2 stride-2 conv: every input voxel feeds exactly its parent voxel."""
    key = ("down2", x.stride)
    kmap = x.cache.kernel_maps.get(key)
    if kmap is not None:
        return kmap
    out_stride = 2 * x.stride
    parent = _floor_to(x.coords, out_stride)  # (M, 4)
    coords = x.cache.coords.get(out_stride)
    if coords is None:
        table = _make_table(parent)
        unique_keys, out_rows = torch.unique(_hash(parent, table.lo, table.extent), return_inverse=True)
        coords = parent.new_empty(unique_keys.numel(), 4)
        coords[out_rows] = parent
        x.cache.coords[out_stride] = coords
    else:
        out_rows = _lookup(x.table(out_stride), parent)
    # offset (dx, dy, dz) in {0, 1}^3, numbered x-major like kernel_offsets(2)
    bits = torch.div(x.coords[:, 1:] - parent[:, 1:], x.stride, rounding_mode="floor")  # (M, 3)
    offset_id = bits[:, 0] * 4 + bits[:, 1] * 2 + bits[:, 2]
    order = torch.argsort(offset_id, stable=True)
    counts = torch.bincount(offset_id, minlength=8).tolist()
    in_idx = list(torch.split(order, counts))
    out_idx = [out_rows[rows] for rows in in_idx]
    kmap = KernelMap(in_idx, out_idx, x.num_voxels, int(coords.shape[0]))
    x.cache.kernel_maps[key] = kmap
    return kmap


def _stride2_k3_map(x: SparseTensor) -> KernelMap:
    """Kernel map of the kernel-3 stride-2 conv: output o at stride 2s reads inputs o + s * {-1, 0, 1}^3."""
    key = ("down3", x.stride)
    kmap = x.cache.kernel_maps.get(key)
    if kmap is not None:
        return kmap
    out_coords = downsample_coords(x)
    offsets = kernel_offsets(3, x.coords.device) * x.stride
    found = x.lookup_shifted(out_coords, offsets)  # (27, M_out)
    in_idx: list[torch.Tensor | None] = []
    out_idx: list[torch.Tensor | None] = []
    for k in range(offsets.shape[0]):
        out_rows = torch.nonzero(found[k] >= 0).squeeze(1)
        in_idx.append(found[k][out_rows])
        out_idx.append(out_rows)
    kmap = KernelMap(in_idx, out_idx, x.num_voxels, int(out_coords.shape[0]))
    x.cache.kernel_maps[key] = kmap
    return kmap


# ---------------------------------------------------------------------------------- convolution


class _GatherGemmScatter(torch.autograd.Function):
    """out[o_k] += in[i_k] @ W[k] for each offset k; backward recomputes the gathers in[i_k] (saves in, W only)
    or, with keep_gathers, reuses the forward's."""

    @staticmethod
    def forward(ctx, features: torch.Tensor, weight: torch.Tensor, kmap: KernelMap, keep_gathers: bool) -> torch.Tensor:
        out = features.new_zeros(kmap.num_out, weight.shape[2])
        gathers = []  # (P_k, C_in) per offset with pairs, kept for backward if keep_gathers
        for k, (i, o) in enumerate(zip(kmap.in_idx, kmap.out_idx)):
            if i is None:
                out += features @ weight[k]
            elif i.numel():
                gathered = features.index_select(0, i)
                out.index_add_(0, o, gathered @ weight[k])
                if keep_gathers:
                    gathers.append(gathered)
        ctx.save_for_backward(features, weight, *gathers)
        ctx.kmap = kmap
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        features, weight, *gathers = ctx.saved_tensors
        kmap: KernelMap = ctx.kmap
        kept = iter(gathers) if gathers else None  # kept gathers, one per offset with pairs, in order
        grad_out = grad_out.contiguous()
        need_in, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_in = torch.zeros_like(features) if need_in else None
        grad_w = torch.zeros_like(weight) if need_w else None
        for k, (i, o) in enumerate(zip(kmap.in_idx, kmap.out_idx)):
            if i is None:
                f, g = features, grad_out
            elif i.numel():
                f = next(kept) if kept is not None else features.index_select(0, i)
                g = grad_out.index_select(0, o)
            else:
                continue
            if need_w:
                grad_w[k] = f.t() @ g
            if need_in:
                gi = g @ weight[k].t()
                if i is None:
                    grad_in += gi
                else:
                    grad_in.index_add_(0, i, gi)
        return grad_in, grad_w, None, None


def sparse_conv(
    features: torch.Tensor, weight: torch.Tensor, kmap: KernelMap, keep_gathers: bool = False
) -> torch.Tensor:
    """(M_in, C_in) features, (K, C_in, C_out) weight -> (M_out, C_out) by gather-GEMM-scatter.

    keep_gathers: backward reuses the forward's gathered inputs (sum_k P_k x C_in more memory held until
    backward) instead of gathering them again; ignored where no gradient is recorded."""
    if weight.shape[0] != len(kmap.in_idx):
        raise ValueError(f"weight has {weight.shape[0]} offsets but the kernel map has {len(kmap.in_idx)}")
    keep = keep_gathers and torch.is_grad_enabled() and (features.requires_grad or weight.requires_grad)
    return _GatherGemmScatter.apply(features, weight, kmap, keep)


class SparseConv3d(nn.Module):
    """Sparse 3D convolution: submanifold (stride 1), downsampling (stride 2) or transposed upsampling.

    stride 1, odd kernel: outputs on the input voxels (submanifold, Graham et al. 2018).
    stride 2, kernel 2 or 3: outputs on the parents floor(c / 2s) * 2s of the occupied voxels.
    transposed, kernel 2 stride 2: outputs on the finer voxels stored when this tensor's level was made.
    Weights (K, C_in, C_out), Kaiming-normal, fan_in = inputs per output (C_in * K; transposed C_in * K / 8).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        stride: int = 1,
        transposed: bool = False,
        bias: bool = False,
        keep_gathers: bool = False,
    ) -> None:
        super().__init__()
        if stride == 1 and (transposed or kernel_size % 2 == 0):
            raise ValueError(f"stride 1 needs an odd kernel and transposed=False; got kernel {kernel_size}")
        if stride == 2 and kernel_size not in ((2,) if transposed else (2, 3)):
            allowed = "2" if transposed else "2 or 3"
            raise ValueError(f"stride 2 {'transposed ' if transposed else ''}conv needs kernel {allowed}")
        if stride not in (1, 2):
            raise ValueError(f"stride must be 1 or 2, got {stride}")
        self.in_channels, self.out_channels = in_channels, out_channels
        self.kernel_size, self.stride, self.transposed = kernel_size, stride, transposed
        self.keep_gathers = keep_gathers  # backward reuses the forward's gathers (sparse_conv)
        volume = kernel_size**3
        self.weight = nn.Parameter(torch.empty(volume, in_channels, out_channels))
        self.bias = nn.Parameter(torch.zeros(out_channels)) if bias else None
        fan_in = max(1, in_channels * volume // (stride**3 if transposed else 1))
        nn.init.normal_(self.weight, std=math.sqrt(2.0 / fan_in))

    def extra_repr(self) -> str:
        kind = "transposed" if self.transposed else ("submanifold" if self.stride == 1 else "strided")
        sizes = f"kernel={self.kernel_size}, stride={self.stride}"
        return f"{self.in_channels}, {self.out_channels}, {sizes}, {kind}"

    def forward(self, x: SparseTensor) -> SparseTensor:
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"expected {self.in_channels} input channels, got {x.features.shape[1]}")
        if self.stride == 1:
            if self.kernel_size == 1:
                out = x.features @ self.weight[0]
            else:
                out = sparse_conv(x.features, self.weight, submanifold_map(x, self.kernel_size), self.keep_gathers)
            y = x.replace(out)
        elif not self.transposed:
            kmap = _stride2_map(x) if self.kernel_size == 2 else _stride2_k3_map(x)
            out = sparse_conv(x.features, self.weight, kmap, self.keep_gathers)
            y = SparseTensor(out, x.cache.coords[2 * x.stride], 2 * x.stride, x.cache)
        else:
            fine = x.stride // 2
            if x.stride % 2 or fine not in x.cache.coords:
                raise ValueError(f"no finer coordinates at stride {fine} stored for this tensor (stride {x.stride})")
            fine_coords = x.cache.coords[fine]
            finer = SparseTensor(x.features.new_empty(fine_coords.shape[0], 0), fine_coords, fine, x.cache)
            out = sparse_conv(x.features, self.weight, _stride2_map(finer).transposed(), self.keep_gathers)
            y = finer.replace(out)
        if self.bias is not None:
            y = y.replace(y.features + self.bias)
        return y


class SparseBatchNorm(nn.BatchNorm1d):
    """BatchNorm1d over the features of all occupied voxels of the batch."""

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.replace(super().forward(x.features))


class SparseReLU(nn.Module):
    """ReLU on the features."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace(F.relu(x.features))


# -------------------------------------------------------------------------------- point <-> voxel


def points_to_voxels(point_features: torch.Tensor, like: SparseTensor, point_index: torch.Tensor) -> SparseTensor:
    """Scatter-mean (N, C) point features into the voxels of `like` given each point's voxel (N,)."""
    return like.replace(scatter_mean(point_features, point_index, like.num_voxels))


def point_voxel_index(x: SparseTensor, point_coords: torch.Tensor) -> torch.Tensor:
    """(N,) row of the voxel at x's stride containing each point; point_coords (N, 4) at stride 1."""
    index = x.cache.point_index.get(x.stride)
    if index is None:
        index = x.lookup(_floor_to(point_coords, x.stride))
        if bool((index < 0).any()):
            raise ValueError("some points fall outside the occupied voxels of this tensor")
        x.cache.point_index[x.stride] = index
    return index


def voxels_to_points(
    x: SparseTensor,
    positions: torch.Tensor,
    batch_index: torch.Tensor,
    mode: Literal["trilinear", "nearest"] = "trilinear",
) -> torch.Tensor:
    """(N, C) features at points: trilinear over the 8 nearest voxel centres present, or the containing voxel.

    `positions` (N, 3) are point positions in stride-1 voxel units (xyz / voxel_size). Trilinear weights come
    from the fractional position between voxel centres (c + s/2); absent neighbours get weight 0 and the rest
    are renormalised (as torchsparse `calc_ti_weights`). The containing voxel is always among the 8 and gets
    at least 1/8 of the weight, so the renormalisation never divides by zero; `nearest` uses it alone.
    The (N, M) interpolation matrix is cached on the tensor's coordinates for the same `positions` object.
    """
    key = (x.stride, mode)
    cached = x.cache.interpolation.get(key)
    if cached is not None and cached[0] is positions and cached[1] is batch_index:
        matrix = cached[2]
    else:
        matrix = interpolation_matrix(x, positions, batch_index, mode)
        x.cache.interpolation[key] = (positions, batch_index, matrix)
    return matrix.to(x.features.dtype) @ x.features  # (N, C); autograd gives matrix^T @ grad


def interpolation_matrix(
    x: SparseTensor,
    positions: torch.Tensor,
    batch_index: torch.Tensor,
    mode: Literal["trilinear", "nearest"] = "trilinear",
) -> torch.Tensor:
    """(N, M) sparse CSR matrix of `voxels_to_points`: a row per point, sorted distinct voxel columns."""
    s, num = x.stride, x.num_voxels
    batch = batch_index.long()[:, None]
    if mode == "nearest":
        corners = torch.zeros(1, 3, dtype=torch.int64, device=positions.device)
        base = torch.floor(positions / s).long()
        weights = positions.new_ones(1, positions.shape[0])
    elif mode == "trilinear":
        corners = kernel_offsets(2, positions.device)  # (8, 3)
        q = positions / s - 0.5  # (N, 3) in voxels of this stride, relative to the centres
        base = torch.floor(q)
        frac = q - base  # (N, 3) in [0, 1)
        base = base.long()
        weights = torch.where(corners[:, None, :].bool(), frac[None], 1 - frac[None]).prod(dim=2)  # (8, N)
    else:
        raise ValueError(f"mode must be 'trilinear' or 'nearest', got {mode!r}")
    idx = x.lookup_shifted(torch.cat([batch, base * s], dim=1), corners * s)  # (8, N)
    present = idx >= 0
    if mode == "nearest" and not bool(present.all()):
        raise ValueError("some points fall outside the occupied voxels of this tensor")
    weights = weights * present
    weights = weights / weights.sum(dim=0, keepdim=True).clamp_min(1e-12)
    cols, order = torch.sort(torch.where(present, idx, num).t(), dim=1)  # (N, 8), absent last
    vals = torch.gather(weights.t(), 1, order)
    keep = cols < num
    crow = torch.zeros(positions.shape[0] + 1, dtype=torch.int64, device=idx.device)
    crow[1:] = torch.cumsum(keep.sum(dim=1), dim=0)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(crow, cols[keep], vals[keep], (positions.shape[0], num), check_invariants=False)
