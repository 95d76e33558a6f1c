"""LiDAR measurement model: ray pattern of a spinning sensor, open3d ray casting, noise, drop and intensity.

Rays come from the sensor's ring elevation table (top ring first) and `azimuth_steps` azimuths per ring,
stored ring-major in azimuth order like a KITTI velodyne file. The static world is one
`open3d.t.geometry.RaycastingScene` per sequence; the moving agents get a small scene per frame and the nearer
hit wins. Intensity = reflectivity x g(|cos incidence|) x range falloff + noise, clipped to [0, 1], with weak
returns read as 0 and quantised to 0.01 as in KITTI remission; a sensor with an intensity response (the HDL-32E,
sensors.intensity_response) then reports that remission on its own scale. Returns beyond `label_range` keep raw id 0
(unlabeled), as the real SemanticKITTI seq-00 labels do past ~50 m.

The measured model (LidarConfig keys after `label_range`, all off in the default world, which then draws no extra
random numbers) adds per-material remission gains and range scatter (surfaces.py), a remission gain per laser,
speckle (log-normal remission per return), range noise growing with range, loss of dark returns (the signal before
noise below `dark_level`) and mixed pixels: at a depth edge between azimuth neighbours one return reads a range
between both surfaces, as a beam footprint straddling the edge does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from u4d_aug.data.sensors import Sensor, intensity_response
from u4d_aug.data.sim.config import LidarConfig
from u4d_aug.data.sim.geometry import MATERIALS, TriangleMesh
from u4d_aug.data.sim.surfaces import material_terms

_DROP = np.array([m.drop_prob for m in MATERIALS], dtype=np.float32)

# Rays blocked by the ego car (roof edge, hood, antenna mounts), measured on the lowest rings of the real
# KITTI seq-00 scans: (azimuth centre deg, half width deg at the top elevation, top elevation deg, widening
# deg per deg below). KITTI loses about 3,500 points per scan there (ring 63 keeps ~56 % of its azimuths).
# Top elevations are those of the simulated beams (after bottom_ring_raise_deg): the rear gap opens at ring 53,
# the hood at ring 57, the side mounts at ring 56 and the right-front mount at ring 47, as in frames 0-5.
_EGO_ZONES = (
    (181.0, 18.0, -19.35, 2.9),  # rear: roof and trunk
    (0.0, 8.7, -21.8, 4.0),  # front: hood
    (-68.0, 9.0, -16.4, 0.0),  # right-front mount
    (-126.0, 4.0, -20.9, 0.0),
    (134.0, 4.0, -20.9, 0.0),
)


@dataclass
class RayPattern:
    """Unit ray directions in the sensor frame, ring-major (top ring first), azimuth counter-clockwise."""

    directions: np.ndarray  # (R, 3) float32
    origins: np.ndarray  # (R, 3) float32 laser origin in the sensor frame (per-ring vertical offset)
    ring: np.ndarray  # (R,) int16 ring index (0 = top)
    keep: np.ndarray  # (R,) bool, False where the ego car blocks the ray
    gain: np.ndarray | None = None  # (R,) float32 remission gain of the ray's laser (None: 1, the basic model)


@dataclass
class Scan:
    """One simulated frame in the sensor frame, points in ray order."""

    points: np.ndarray  # (N, 4) float32 x, y, z, remission (on the sensor's intensity scale, [0, 1])
    semantic: np.ndarray  # (N,) uint16 raw SemanticKITTI ids
    instance: np.ndarray  # (N,) uint16
    ring: np.ndarray  # (N,) int16


def azimuth_steps(sensor: Sensor, cfg: LidarConfig) -> int:
    """Azimuth steps per ring: the configured number, else the sensor's usual one at 10 Hz."""
    if cfg.azimuth_steps is not None:
        return int(cfg.azimuth_steps)
    return {"hdl64": 2083, "hdl32": 1085}.get(sensor.name, 2 * sensor.width)


def ray_pattern(sensor: Sensor, cfg: LidarConfig, rng: np.random.Generator) -> RayPattern:
    """Ray directions from the sensor's ring table, small per-ring elevation/azimuth offsets (calibration)."""
    rings = sensor.num_rings
    elevation_deg = np.asarray(sensor.elevations_deg) + rng.normal(0.0, cfg.elevation_jitter_deg, rings)
    if sensor.name == "hdl64":
        elevation_deg[57:] += cfg.bottom_ring_raise_deg * np.linspace(0.0, 1.0, rings - 57 + 1)[1:]
    elevation = np.radians(elevation_deg)
    offset_z = cfg.laser_offset[0] + cfg.laser_offset[1] * rng.standard_normal(rings)
    # the table holds median point elevations seen from the origin; aim each beam so that its typical return
    # (ground hit for down-looking rings, ~15 m otherwise) keeps that elevation despite the raised origin
    typical = np.where(elevation < np.radians(-5.0), cfg.sensor_height / np.sin(np.abs(elevation) + 1e-6), 15.0)
    elevation = elevation - offset_z / typical
    steps = azimuth_steps(sensor, cfg)
    azimuth = np.radians(cfg.azimuth_start_deg + rng.normal(0.0, cfg.azimuth_jitter_deg, rings))[:, None] + (
        2.0 * np.pi * (np.arange(steps) + 0.5) / steps
    )  # (H, A)
    el = np.broadcast_to(elevation[:, None], azimuth.shape)
    directions = np.stack([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)], axis=-1)
    keep = np.ones(azimuth.shape, dtype=bool)
    if cfg.ego_mask and sensor.name == "hdl64":
        el_deg = np.degrees(el)
        az_deg = np.degrees(azimuth)
        for center, half, top, widen in _EGO_ZONES:
            delta = np.abs((az_deg - center + 180.0) % 360.0 - 180.0)
            keep &= ~((el_deg < top) & (delta < half + widen * (top - el_deg)))
    origins = np.zeros((rings, steps, 3))
    origins[..., 2] = offset_z[:, None]
    gain = None
    if cfg.ring_gain_spread > 0:  # drawn last: the basic pattern keeps its random numbers
        sigma = cfg.ring_gain_spread
        gain = np.repeat(np.exp(sigma * rng.standard_normal(rings) - sigma**2 / 2), steps).astype(np.float32)
    return RayPattern(
        directions=directions.reshape(-1, 3).astype(np.float32),
        origins=origins.reshape(-1, 3).astype(np.float32),
        ring=np.repeat(np.arange(rings, dtype=np.int16), steps),
        keep=keep.reshape(-1),
        gain=gain,
    )


def azimuth_neighbours(ring: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(K,) index among the kept rays of each kept ray's next azimuth step on its ring, -1 where that ray is masked."""
    rings = int(ring.max()) + 1
    steps = len(ring) // rings
    position = np.full(len(ring), -1, dtype=np.int64)
    kept = np.flatnonzero(keep)
    position[kept] = np.arange(len(kept))
    following = (kept // steps) * steps + (kept % steps + 1) % steps
    return position[following]


def make_scene(mesh: TriangleMesh) -> o3d.t.geometry.RaycastingScene | None:
    """RaycastingScene holding one mesh (None when it has no triangles)."""
    if mesh.num_triangles == 0:
        return None
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(mesh.triangles, dtype=np.uint32)),
    )
    return scene


def _cast(scene, rays: np.ndarray, nthreads: int):
    out = scene.cast_rays(o3d.core.Tensor(rays), nthreads=nthreads)
    return out["t_hit"].numpy(), out["primitive_ids"].numpy(), out["primitive_normals"].numpy()


@dataclass
class _Hits:
    """The surface each ray of a sweep hits first (`LidarSimulator._hits`), in the order of the kept rays."""

    t_hit: np.ndarray  # (R,) float32 distance along the ray, 0 where nothing is hit
    hit: np.ndarray  # (R,) bool
    normal: np.ndarray  # (R, 3) surface normal
    semantic: np.ndarray  # (R,) raw SemanticKITTI id
    instance: np.ndarray  # (R,)
    material: np.ndarray  # (R,) index into geometry.MATERIALS
    reflectivity: np.ndarray  # (R,)


class LidarSimulator:
    """Static scene built once; `scan(pose, dynamic_mesh, rng)` casts one sweep."""

    def __init__(
        self, static: TriangleMesh, sensor: Sensor, cfg: LidarConfig, pattern: RayPattern, nthreads: int = 0
    ) -> None:
        self.static = static
        self.sensor = sensor
        self.cfg = cfg
        self.pattern = pattern
        self.nthreads = nthreads
        self.scene = make_scene(static)
        keep = pattern.keep
        self._kept = (
            np.ascontiguousarray(pattern.directions[keep]),
            np.ascontiguousarray(pattern.origins[keep, 2]),
            pattern.ring[keep],
        )
        self._terms = material_terms(cfg.surface_model, cfg.speckle)
        self._ring_gain = None if pattern.gain is None else pattern.gain[keep]
        self._next = azimuth_neighbours(pattern.ring, keep) if cfg.mixed_pixel_prob > 0 else None

    def scan(self, pose: np.ndarray, dynamic: TriangleMesh | None, rng: np.random.Generator) -> Scan:
        """Cast the sweep from LiDAR pose (4, 4) world<-sensor; the nearest hit of static/dynamic wins."""
        rays = self._rays(pose)
        hits = self._hits(rays, dynamic)
        normal = hits.normal
        cos_inc = np.abs(normal[:, 0] * rays[:, 3] + normal[:, 1] * rays[:, 4] + normal[:, 2] * rays[:, 5])
        distance = self._distance(hits, rng)
        keep = self._returned(hits, distance, cos_inc, rng)
        intensity, keep = self._intensity(hits, distance, cos_inc, keep, rng)
        return self._points(np.flatnonzero(keep), distance, intensity, hits)

    def _rays(self, pose: np.ndarray) -> np.ndarray:
        """(R, 6) world origins and directions of the ego-masked rays from LiDAR pose (4, 4) world<-sensor."""
        local, offset_z, _ = self._kept  # (R, 3) unit directions, (R,) laser height
        rot = pose[:3, :3].astype(np.float32)
        rays = np.empty((len(local), 6), dtype=np.float32)
        for axis in range(3):  # explicit 3x3 products: much faster than (R, 3) @ (3, 3) in numpy
            rays[:, 3 + axis] = local[:, 0] * rot[axis, 0] + local[:, 1] * rot[axis, 1] + local[:, 2] * rot[axis, 2]
            rays[:, axis] = offset_z * rot[axis, 2] + np.float32(pose[axis, 3])
        return rays

    def _hits(self, rays: np.ndarray, dynamic: TriangleMesh | None) -> _Hits:
        """The nearer hit of the static scene and the moving agents along each ray, with its surface's labels."""
        t_hit, prim, normal = _cast(self.scene, rays, self.nthreads)
        from_dynamic = None
        if dynamic is not None and dynamic.num_triangles:
            t_dyn, prim_dyn, normal_dyn = _cast(make_scene(dynamic), rays, self.nthreads)
            from_dynamic = t_dyn < t_hit
            t_hit = np.where(from_dynamic, t_dyn, t_hit)
            prim = np.where(from_dynamic, prim_dyn, prim)
            normal[from_dynamic] = normal_dyn[from_dynamic]
        hit = np.isfinite(t_hit)
        prim = np.where(hit, prim, 0).astype(np.int64)
        t_hit = np.where(hit, t_hit, np.float32(0.0))
        static = self.static
        take = prim if from_dynamic is None else np.where(from_dynamic, 0, prim)
        semantic, instance = static.semantic[take], static.instance[take]
        material, reflectivity = static.material[take], static.reflectivity[take]
        if from_dynamic is not None and from_dynamic.any():
            d = prim[from_dynamic]
            semantic[from_dynamic], instance[from_dynamic] = dynamic.semantic[d], dynamic.instance[d]
            material[from_dynamic], reflectivity[from_dynamic] = dynamic.material[d], dynamic.reflectivity[d]
        return _Hits(t_hit, hit, normal, semantic, instance, material, reflectivity)

    def _distance(self, hits: _Hits, rng: np.random.Generator) -> np.ndarray:
        """Measured range of each ray: Gaussian noise plus penetration into porous material (leaves), range-growing
        noise and mixed pixels (measured model)."""
        cfg, t_hit, material = self.cfg, hits.t_hit, hits.material
        n = len(t_hit)
        distance = t_hit + np.float32(cfg.range_noise) * rng.standard_normal(n, dtype=np.float32)
        distance += self._terms.penetration[material] * rng.standard_exponential(n, dtype=np.float32)
        if cfg.range_noise_per_m > 0:
            distance += np.float32(cfg.range_noise_per_m) * t_hit * rng.standard_normal(n, dtype=np.float32)
        if self._next is not None:
            distance = mixed_pixels(distance, t_hit, hits.hit, self._next, cfg, rng)
        return distance

    def _returned(self, hits: _Hits, distance: np.ndarray, cos_inc: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(R,) bool, the rays that return: drop at random, by material (glass, spokes), at grazing incidence; then
        the range limits."""
        cfg = self.cfg
        u = rng.random((3, len(distance)), dtype=np.float32)
        keep = hits.hit & (u[0] >= cfg.random_drop) & (u[1] >= _DROP[hits.material])
        keep &= u[2] * np.float32(cfg.grazing_cos) >= np.float32(cfg.grazing_cos) - cos_inc
        keep &= (distance >= self.sensor.min_range) & (distance <= self.sensor.max_range)
        return keep

    def _intensity(
        self, hits: _Hits, distance: np.ndarray, cos_inc: np.ndarray, keep: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """(intensity, keep without the dark returns lost): reflectivity x g(|cos|) x falloff(range) + noise; weak
        returns read 0; 0.01 steps; on the sensor's own scale."""
        cfg, material, n = self.cfg, hits.material, len(distance)
        incidence = np.power(
            np.minimum(cos_inc / np.float32(cfg.incidence_ref), np.float32(1.0)),
            np.float32(cfg.intensity_incidence_exp),
        )
        falloff = np.exp(-np.maximum(distance - np.float32(cfg.falloff_start), 0) / np.float32(cfg.falloff_scale))
        intensity = hits.reflectivity * incidence * falloff
        measured = cfg.surface_model != "basic"
        if measured:
            intensity = intensity * self._terms.gain[material]
        if self._ring_gain is not None:
            intensity = intensity * self._ring_gain
        if cfg.dark_drop > 0:  # too little light comes back: the return is lost
            lost = np.float32(cfg.dark_drop) * np.clip(1.0 - intensity / np.float32(cfg.dark_level), 0.0, 1.0)
            keep = keep & (rng.random(n, dtype=np.float32) >= lost)
        if measured or cfg.speckle > 0:
            sigma = self._terms.speckle[material]
            intensity = intensity * np.exp(sigma * rng.standard_normal(n, dtype=np.float32) - sigma * sigma / 2)
        intensity += np.float32(cfg.intensity_noise) * rng.standard_normal(n, dtype=np.float32)
        low, high = cfg.zero_threshold
        threshold = np.float32(low) + np.float32(high - low) * rng.random(n, dtype=np.float32)
        zero = (intensity < threshold) | (rng.random(n, dtype=np.float32) < self._terms.zero_prob[material])
        intensity = np.where(zero, np.float32(0.0), intensity)
        intensity = np.clip(
            np.floor(intensity / np.float32(cfg.intensity_step)) * np.float32(cfg.intensity_step), 0.0, 0.99
        )
        if not self.sensor.reports_remission:  # the sensor's own intensity scale (HDL-32E: nuScenes')
            intensity = intensity_response(self.sensor, intensity)
        return intensity, keep

    def _points(self, sel: np.ndarray, distance: np.ndarray, intensity: np.ndarray, hits: _Hits) -> Scan:
        """The returns `sel` (indices of the kept rays) as a Scan in the sensor frame, labels cut at label_range."""
        local, offset_z, ring = self._kept
        points = np.empty((len(sel), 4), dtype=np.float32)
        d = distance[sel]
        points[:, 0] = local[sel, 0] * d
        points[:, 1] = local[sel, 1] * d
        points[:, 2] = local[sel, 2] * d + offset_z[sel]
        points[:, 3] = intensity[sel]
        semantic, instance = hits.semantic[sel], hits.instance[sel]
        if self.cfg.label_range is not None:  # the annotation stops short of the sensor's reach
            far = d > np.float32(self.cfg.label_range)
            semantic[far], instance[far] = 0, 0
        return Scan(points, semantic, instance, ring[sel])


def mixed_pixels(
    distance: np.ndarray, t_hit: np.ndarray, hit: np.ndarray, following: np.ndarray, cfg: LidarConfig, rng
) -> np.ndarray:
    """Ranges with mixed pixels: where azimuth neighbours (`following`) hit surfaces more than `mixed_pixel_jump`
    apart, with `mixed_pixel_prob` one of the two (either, at random) reads a range 15-85 % of the way across."""
    n = len(distance)
    other = np.maximum(following, 0)
    edge = (following >= 0) & hit & hit[other] & (np.abs(t_hit[other] - t_hit) > np.float32(cfg.mixed_pixel_jump))
    u = rng.random((3, n), dtype=np.float32)
    pick = np.flatnonzero(edge & (u[0] < np.float32(cfg.mixed_pixel_prob)))
    near = np.minimum(t_hit[pick], t_hit[other[pick]])
    far = np.maximum(t_hit[pick], t_hit[other[pick]])
    target = np.where(u[1, pick] < 0.5, pick, other[pick])
    out = distance.copy()
    out[target] = near + (np.float32(0.15) + np.float32(0.7) * u[2, pick]) * (far - near) + (distance - t_hit)[target]
    return out
