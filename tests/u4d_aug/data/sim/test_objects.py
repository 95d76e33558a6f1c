"""Object models of the simulated world (u4d_aug/data/sim/objects.py): street-object sizes, one label and instance per
object, limbs that can walk, placing by yaw and translation, canopies above the sidewalk."""

from __future__ import annotations

import numpy as np
import pytest

from u4d_aug.data.sim import objects
from u4d_aug.data.sim.geometry import MAT, RAW, MeshBuilder


@pytest.mark.parametrize("kind", ["sedan", "hatch", "suv"])
def test_cars_are_kitti_sized_one_object_standing_on_their_wheels(kind):
    for seed in range(3):
        car = objects.car(np.random.default_rng(seed), "car", 3, kind=kind)
        length, width, height = np.ptp(car.vertices, axis=0)
        assert 3.7 <= length <= 4.95 and 1.65 <= width <= 1.95 and 1.35 <= height <= 1.85, (length, width, height)
        assert 0.0 <= car.vertices[:, 2].min() < 0.02  # the wheels touch the ground
        assert abs(car.vertices[:, 0].max() + car.vertices[:, 0].min()) < 0.1  # centred on the origin
        assert set(car.semantic.tolist()) == {RAW["car"]} and set(car.instance.tolist()) == {3}
        assert set(car.material.tolist()) == {MAT["car_paint"], MAT["car_glass"], MAT["tire"]}


def test_people_have_limbs_to_walk_with_and_none_when_seated():
    for seed in range(3):
        person, parts = objects.person(np.random.default_rng(seed), "person", 2)
        assert len(parts) == len(person.vertices) and set(parts.tolist()) == {
            objects.PART_RIGID, objects.PART_LEFT_LEG, objects.PART_RIGHT_LEG, objects.PART_LEFT_ARM,
            objects.PART_RIGHT_ARM,
        }  # fmt: skip
        assert person.vertices[:, 2].min() == 0.0 and 1.5 < np.ptp(person.vertices[:, 2]) < 1.9
        seated, seated_parts = objects.person(np.random.default_rng(seed), "person", 2, seated=True)
        assert set(seated_parts.tolist()) == {objects.PART_RIGID}
        assert np.ptp(seated.vertices[:, 2]) < np.ptp(person.vertices[:, 2])  # no legs under the hip


@pytest.mark.parametrize(("label", "motor"), [("bicyclist", False), ("motorcyclist", True)])
def test_a_rider_and_the_two_wheeler_are_one_object(label, motor):
    rider, parts = objects.rider(np.random.default_rng(0), label, 7, motor=motor)
    assert set(rider.semantic.tolist()) == {RAW[label]} and set(rider.instance.tolist()) == {7}
    assert not parts.any() and len(parts) == len(rider.vertices)  # rides rigidly
    assert 1.5 < np.ptp(rider.vertices[:, 0]) < 2.4 and rider.vertices[:, 2].min() >= 0.0


def test_place_turns_about_z_then_moves():
    car = objects.car(np.random.default_rng(0), "car", 1)
    placed = objects.place(car, np.pi / 2, (1.0, 2.0, 3.0))
    x, y, z = car.vertices.T
    np.testing.assert_allclose(placed.vertices, np.column_stack([1.0 - y, 2.0 + x, 3.0 + z]), atol=1e-5)
    assert np.array_equal(placed.triangles, car.triangles) and np.array_equal(placed.semantic, car.semantic)


def test_a_street_tree_lifts_its_canopy_above_the_clearance():
    mb = MeshBuilder()
    objects.tree(mb, np.random.default_rng(0), (5.0, 2.0), ground_z=0.3, clearance=2.5)
    tree = mb.build()
    assert set(tree.semantic.tolist()) == {RAW["vegetation"], RAW["trunk"]}
    leaves = np.unique(tree.triangles[tree.semantic == RAW["vegetation"]])
    assert tree.vertices[leaves, 2].min() >= 0.3 + 2.5 - 1e-5
    trunk = np.unique(tree.triangles[tree.semantic == RAW["trunk"]])
    assert np.isclose(tree.vertices[trunk, 2].min(), 0.3)  # standing on the ground
    assert tree.vertices[trunk, 2].max() > tree.vertices[leaves, 2].min()  # and reaching into the canopy
