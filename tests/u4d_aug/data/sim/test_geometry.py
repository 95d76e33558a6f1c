"""Labelled triangle meshes of the simulated world (u4d_aug/data/sim/geometry.py): SemanticKITTI ids, closed
outward primitives, the builder and its warp, meshes taken apart and put together again."""

from __future__ import annotations

import numpy as np

from u4d_aug.data.labels import SEMANTICKITTI_RAW_NAMES
from u4d_aug.data.sim import objects
from u4d_aug.data.sim.geometry import (
    MAT,
    MATERIALS,
    RAW,
    MeshBuilder,
    add_mesh,
    box,
    concat_meshes,
    densify,
    merge,
    quad,
    sample_reflectivity,
    strip,
    transform,
)
from u4d_aug.data.sim.streets import Bend, Warp


def signed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Volume enclosed by a closed mesh, positive when its triangles face outwards (divergence theorem)."""
    a, b, c = (vertices[triangles[:, k]].astype(np.float64) for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def triangle_set(mesh) -> list[tuple]:
    """The triangles of a mesh as sorted (vertex coordinates, label, instance, material, reflectivity) tuples."""
    corners = np.sort(mesh.vertices[mesh.triangles].reshape(len(mesh.triangles), 9), axis=1)
    rows = np.column_stack([corners, mesh.semantic, mesh.instance, mesh.material, mesh.reflectivity])
    return sorted(map(tuple, rows.tolist()))


def test_raw_ids_are_semantickitti() -> None:
    for name, raw in RAW.items():
        assert SEMANTICKITTI_RAW_NAMES[raw] == name


def test_warp_bends_surfaces_and_carries_objects_rigidly() -> None:
    warp = Warp(Bend(np.array([10.0]), np.array([2 * np.pi / 200]), np.array([0.0])), Bend(*np.zeros((3, 0))))
    mb = MeshBuilder(warp)
    mb.axis = 0  # objects belong to the x-street
    xs = np.linspace(0.0, 100.0, 51)
    band = strip(np.column_stack([xs, np.full(51, 5.0)]), np.column_stack([xs, np.full(51, 8.0)]), 0.1)
    mb.add(band, "sidewalk", "paving", 0.3)
    car = objects.place(objects.car(np.random.default_rng(0), "car", 5), 0.0, (25.0, 3.0, 0.0))
    add_mesh(mb, car)
    mesh = mb.build()
    n = len(band[0])
    # surfaces follow the bent street point by point
    np.testing.assert_allclose(mesh.vertices[:n, :2], warp.points(band[0][:, :2]), atol=1e-4)
    # the car keeps its shape and turns with the street: heading atan(df/dx) at its centre, 12.5 deg
    moved = mesh.vertices[n:].astype(np.float64)
    original = car.vertices.astype(np.float64)
    np.testing.assert_allclose(moved[:, 2], original[:, 2], atol=1e-5)
    pairs = np.random.default_rng(1).integers(0, len(original), (200, 2))
    dist = np.linalg.norm(moved[pairs[:, 0]] - moved[pairs[:, 1]], axis=1)
    np.testing.assert_allclose(dist, np.linalg.norm(original[pairs[:, 0]] - original[pairs[:, 1]], axis=1), atol=1e-4)
    axis = np.linalg.svd(moved[:, :2] - moved[:, :2].mean(axis=0), full_matrices=False)[2][0]
    heading = np.degrees(np.arctan2(axis[1], axis[0])) % 180.0
    expected = np.degrees(np.arctan(10.0 * 2 * np.pi / 200 * np.cos(2 * np.pi * 25.0 / 200)))
    assert abs(heading - expected) < 0.5, (heading, expected)


def test_box_is_closed_and_faces_outwards():
    vertices, triangles = box((2.0, 4.0, 6.0), center=(10.0, -3.0, 1.0))
    assert np.isclose(signed_volume(vertices, triangles), 48.0)
    np.testing.assert_allclose(vertices.mean(axis=0), [10.0, -3.0, 1.0])
    turned = transform((vertices, triangles), yaw=0.7, translation=(5.0, 5.0, 0.0))
    assert np.isclose(signed_volume(*turned), 48.0)  # rotating and moving keep volume and orientation
    open_vertices, open_triangles = box((2.0, 4.0, 6.0), bottom=False)
    assert len(open_triangles) == 10 and not np.any(np.all(open_vertices[open_triangles][..., 2] < 0, axis=1))


def test_quad_faces_the_side_it_is_counter_clockwise_from():
    vertices, triangles = quad((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0))
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    np.testing.assert_allclose(np.cross(b - a, c - a), [[0, 0, 1], [0, 0, 1]])  # seen from +z


def test_densify_keeps_the_corners_and_shortens_every_edge():
    square = np.array([(0.0, 0.0), (10.0, 0.0), (10.0, 4.0), (0.0, 4.0)])
    closed = densify(square, 3.0, closed=True)
    edges = np.linalg.norm(np.diff(np.vstack([closed, closed[:1]]), axis=0), axis=1)
    assert edges.max() <= 3.0 and len(closed) == 4 + 2 + 4 + 2  # 4 pieces per 10 m side, 2 per 4 m side
    assert all(any(np.allclose(corner, p) for p in closed) for corner in square)
    line = densify(square[:2], 3.0)
    np.testing.assert_allclose(line[:, 0], [0.0, 2.5, 5.0, 7.5, 10.0])  # the open end is kept too


def test_builder_and_concat_shift_the_vertex_indices_and_repeat_the_labels():
    mb = MeshBuilder()
    mb.add(merge(box((1, 1, 1)), box((1, 1, 1), center=(3, 0, 0))), "car", "car_paint", 0.2, instance=4)
    mb.add(quad((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)), "road", "asphalt", np.array([0.1, 0.3]))
    mesh = mb.build()
    assert len(mesh.vertices) == 20 and mesh.num_triangles == 26 and mesh.triangles.max() == 19
    assert mesh.semantic.tolist() == [RAW["car"]] * 24 + [RAW["road"]] * 2
    assert mesh.instance.tolist() == [4] * 24 + [0, 0] and mesh.material[-1] == MAT["asphalt"]
    np.testing.assert_allclose(mesh.reflectivity[-2:], [0.1, 0.3])
    both = concat_meshes([mesh, MeshBuilder().build(), mesh])
    assert both.num_triangles == 52 and both.triangles[26:].min() == 20
    np.testing.assert_array_equal(both.vertices[both.triangles[26:]], mesh.vertices[mesh.triangles])


def test_add_mesh_takes_a_mesh_apart_and_the_builder_puts_it_together_again():
    car = objects.car(np.random.default_rng(0), "car", 5)
    mb = MeshBuilder()
    add_mesh(mb, car)
    assert triangle_set(mb.build()) == triangle_set(car)


def test_object_reflectivity_follows_its_material():
    rng = np.random.default_rng(0)
    facade = np.concatenate([sample_reflectivity(rng, "facade", 3) for _ in range(2000)])
    assert abs(facade.mean() - MATERIALS[MAT["facade"]].reflectivity) < 0.01
    glass = sample_reflectivity(rng, "glass", 5000)
    assert glass.min() >= 0.01 and glass.max() <= 1.0 and glass.dtype == np.float32
