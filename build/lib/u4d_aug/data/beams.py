"""How many laser beams recorded a scan, read from the order of its points, to catch a scan projected with the
wrong sensor (a 32-beam scan as an HDL-64E gives a range image with every other row empty).

Spinning sensors store a scan in one of two orders, and each shows the beam count:
- ring by ring (KITTI's HDL-64E files, the simulated world): each ring is one 360-degree azimuth sweep, so the count
  of azimuth wrap-arounds + 1 is the beam count (a few extra wraps come from returns next to the sensor);
- firing by firing (nuScenes' HDL-32E files): the beams fire bottom to top at every azimuth step, so the scan is
  a run of groups whose elevation climbs and then drops; the largest group size that is not rare is the beam count
  (groups with missing returns are smaller, two groups merged by a missing drop are rare).
A file in neither order (shuffled, cropped, generated) has no estimate, and nothing is checked.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from u4d_aug.data.sensors import Sensor

log = logging.getLogger(__name__)

MIN_BEAMS, MAX_BEAMS = 8, 160  # what a spinning sensor may have; estimates outside are no estimate
RING_ORDER_MIN_POINTS = 200  # a ring-by-ring sweep holds at least this many points on average
MIN_GROUPS = 20  # firing groups a firing-order scan shows at least
MIN_RISING = 0.75  # share of the steps inside firing groups that climb (nuScenes keyframe 0.9x; shuffled ~0.5)
FULL_SHARE = 0.02  # a full group is at least this common (nuScenes keyframe: 90 % of the groups; 2.4 % once the
# ego returns within 1 m are dropped), a merged one rarer (33 points: 1.2 %)
MISMATCH_RATIO = 1.3  # beam counts further apart than this are a different sensor (KITTI files show 64-68 wraps)


def beams_from_ring_order(points: np.ndarray) -> int | None:
    """Azimuth wrap-arounds + 1 of a ring-by-ring scan (N, >=3), or None when the points are not in that order."""
    if len(points) < MIN_BEAMS * RING_ORDER_MIN_POINTS:
        return None
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    step = np.diff(azimuth)
    wraps = max(int((step < -math.pi).sum()), int((step > math.pi).sum()))  # sweeps run either way round
    beams = wraps + 1
    if not MIN_BEAMS <= beams <= MAX_BEAMS or len(points) / beams < RING_ORDER_MIN_POINTS:
        return None
    return beams


def beams_from_firing_order(points: np.ndarray) -> int | None:
    """Largest common size of the bottom-to-top firing groups of a firing-order scan (N, >=3), or None when it has
    none (a group ends where the elevation drops by more than half the scan's vertical spread)."""
    if len(points) < MIN_BEAMS * MIN_GROUPS:
        return None
    xyz = points[:, :3].astype(np.float64)
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    low, high = np.percentile(elevation, [5, 95])
    step = np.diff(elevation)
    drops = step < -(high - low) / 2
    starts = np.flatnonzero(drops) + 1
    sizes = np.diff(np.concatenate([[0], starts, [len(points)]]))[1:-1]  # whole groups only
    if len(sizes) < MIN_GROUPS or (step[~drops] > 0).mean() < MIN_RISING:  # shuffled points drop at random too
        return None
    counts = np.bincount(sizes)
    common = np.flatnonzero(counts >= FULL_SHARE * len(sizes))  # sizes seen often enough not to be merged groups
    beams = int(common.max()) if len(common) else 0
    if not MIN_BEAMS <= beams <= MAX_BEAMS:
        return None
    return beams


def estimate_beams(points: np.ndarray, ring: np.ndarray | None = None) -> int | None:
    """Beam count of a scan: from its ring column when the file has one, else from the order of its points."""
    if ring is not None and len(ring):
        return int(ring.max()) + 1
    return beams_from_firing_order(points) or beams_from_ring_order(points)  # ring order shows no firing groups


def check_beams(points: np.ndarray, sensor: Sensor, source: str, ring: np.ndarray | None = None) -> int | None:
    """Warn when a scan's beam count is not the sensor's rows (e.g. a 32-beam scan projected as the HDL-64E)."""
    beams = estimate_beams(points, ring)
    if beams is not None and max(beams, sensor.height) / min(beams, sensor.height) > MISMATCH_RATIO:
        log.warning(
            "%s: the scan looks recorded by a %d-beam sensor, but it is projected as %s with %d rows; choose the "
            "sensor that recorded it (e.g. --sensor hdl32 / sensor=hdl32) or the range image will have %s rows",
            source,
            beams,
            sensor.name,
            sensor.height,
            "empty" if beams < sensor.height else "merged",
        )
    return beams
