"""Typed configuration of the simulated world: streets, lots, objects, agents, ego motion and the LiDAR model.

Defaults are tuned against the real SemanticKITTI seq-00 scans (../shared/data/real/SOURCES.md): class shares,
range histogram, per-class remission. Override with a yaml file (configs/sim/*.yaml) or `key.sub=value`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Literal

from u4d_aug.errors import InputError
from u4d_aug.validate import check_finite_config, check_positive


@dataclass
class StreetConfig:
    """Street lattice and cross-section (distances in metres, from the street centre line outwards)."""

    block_size: tuple[float, float] = (60.0, 120.0)  # spacing of parallel streets
    # wide residential carriageways: road + parking take 48 % of ring 39 (8.9 m ground range) in real seq 00,
    # 38 % with (3.4, 4.0) m lanes, 40 % with these; range JS over 4 seeds x 8 places 0.116 -> 0.104
    lane_width: tuple[float, float] = (3.8, 4.5)
    main_street_prob: float = 0.15  # two lanes per direction, centre line, more traffic
    parking_prob: float = 0.3  # a street side has a parking strip with parked vehicles
    parking_label_prob: float = 0.75  # the strip is marked (raw 44 parking) rather than plain road
    parking_width: tuple[float, float] = (2.0, 2.5)
    # narrow residential sidewalks: real seq 00 has hedges 6-7 m and facades 9-12 m from the sensor
    sidewalk_width: tuple[float, float] = (2.5, 4.5)
    grass_strip_prob: float = 0.05  # a terrain strip with street trees between curb and sidewalk
    curb_height: tuple[float, float] = (0.10, 0.16)
    corner_radius: tuple[float, float] = (3.0, 8.0)
    center_line_prob: float = 0.5  # residential streets with a dashed centre line
    crosswalk_prob: float = 0.3  # zebra stripes at a street end
    median_prob: float = 0.3  # raised traffic island (raw 49 other-ground) in a main street segment
    # bending streets: the lattice plane is sheared so that x-streets swing sideways by a smooth offset of x
    # (y-streets likewise); two sines per street family, amplitudes capped by slope and curve radius
    bend_amplitude: tuple[float, float] = (8.0, 22.0)  # m, per sine
    bend_wavelength: tuple[float, float] = (160.0, 420.0)  # m
    straight_prob: float = 0.2  # a street family stays straight
    bend_max_slope: float = 0.36  # max |d offset / ds|: heading swing about +-20 deg
    bend_min_radius: float = 70.0  # m, smallest centre-line curve radius
    # gentle hills (streets.Hills): three plane waves, capped by grade and curvature; real seq 00 is not flat
    # (ground 0.7 m lower 30 m to the left, 0.2 m higher ahead), which spreads the ground rings over 20-40 m
    hill_amplitude: tuple[float, float] = (0.5, 2.0)  # m, per wave
    hill_wavelength: tuple[float, float] = (120.0, 300.0)  # m
    hill_max_grade: float = 0.05  # max |grad h|
    hill_min_radius: float = 500.0  # m, smallest vertical curve radius
    flat_prob: float = 0.1  # the world is flat
    # --- street types (scenes.py); the defaults keep the seq-00 layout bit for bit
    main_lanes: tuple[int, int] = (2, 2)  # lanes per direction of a main street (arterials: 2-3)
    grass_width: tuple[float, float] = (1.0, 2.0)  # m, terrain strip between curb and sidewalk paving
    median_terrain_prob: float = 0.0  # a traffic island is a lawn (terrain) with trees, not paved other-ground
    sidewalk_material: Literal["paving", "concrete", "cobble"] = "paving"
    signal_prob: float = 0.0  # traffic lights (pole + traffic-sign heads) at the corners of main-street crossings
    roundabout_prob: float = 0.0  # a crossing of two residential streets is a roundabout
    roundabout_radius: tuple[float, float] = (3.0, 5.0)  # m, central island (capped by the room between the kerbs)


@dataclass
class LotConfig:
    """What stands behind the sidewalks: building lots, gardens, parking lots."""

    frontage: tuple[float, float] = (12.0, 28.0)  # lot width along the street
    depth: tuple[float, float] = (22.0, 34.0)
    # lot kinds: house (detached, front yard), row (facade at the sidewalk), garden, parking lot, commercial
    kind_weights: tuple[float, float, float, float, float] = (0.55, 0.12, 0.15, 0.08, 0.10)
    floor_height: tuple[float, float] = (2.8, 3.4)
    house_floors: tuple[int, int] = (2, 4)
    row_floors: tuple[int, int] = (3, 6)
    setback: tuple[float, float] = (1.5, 5.0)  # house distance from the sidewalk
    row_setback: tuple[float, float] = (1.0, 3.0)  # row-house facade distance from the sidewalk
    front_fence_prob: float = 0.9  # fence, wall or hedge at the front of a house lot
    hedge_prob: float = 0.8  # that front boundary is a hedge (gardens: always)
    # m; below the sensor (1.8 m), as in real seq 00 where the upper rings see over the hedges at 6-7 m
    hedge_height: tuple[float, float] = (0.9, 1.8)
    yard_trees: tuple[int, int] = (2, 5)  # tall canopies behind the houses hide the far field
    yard_bushes: tuple[int, int] = (4, 10)
    courtyard_tree_area: float = 120.0  # m^2 of back courtyard per tree
    # garden shed / bin shelter in a front yard (raw 52 other-structure; real seq 00: 1.2 % of the points)
    shed_prob: float = 0.3
    shrub_bed_prob: float = 0.6  # a row of shrubs along the front of a house yard (real seq 00: 22 % vegetation)
    other_ground_prob: float = 0.05  # gravel/paved yard (raw 49) instead of grass (real seq 00: none)
    # yard under low shrubs (vegetation) instead of lawn (terrain); real seq 00: 22 % vegetation, 2 % terrain
    ground_cover_prob: float = 0.75
    # --- street types (scenes.py): whole blocks of another use, and driveways; 0 = never (the default world)
    park_block_prob: float = 0.0  # the block is a park: lawn, trees, paths, benches, lamps
    plaza_block_prob: float = 0.0  # the block is a paved square with planters, benches, kiosks
    parking_block_prob: float = 0.0  # the block is one parking lot with rows of cars and lawn islands
    driveway_prob: float = 0.0  # a house lot has a paved driveway (raw 44 parking) from the sidewalk


@dataclass
class StreetObjectConfig:
    """Street furniture and parked vehicles (spacings in metres along a street side)."""

    tree_spacing: tuple[float, float] = (6.0, 12.0)
    street_tree_prob: float = 0.65  # a street side has a tree row
    tree_clearance: float = 2.5  # m, lowest canopy point of a street tree above the sidewalk
    # m, street tree distance from the curb without a grass strip: at the back of the sidewalk (capped at width
    # - 0.6 m), as real seq 00 shows no trunk within 10 m of the sensor
    tree_offset: float = 3.0
    pole_spacing: tuple[float, float] = (22.0, 35.0)
    sign_prob: float = 0.7  # traffic sign near a street end
    object_prob: float = 0.5  # trash bin / bollards / box (raw 99 other-object) per 20 m
    parked_occupancy: tuple[float, float] = (0.2, 0.5)
    # parked vehicle kinds along parking strips: car, truck, other-vehicle (van), motorcycle
    parked_weights: tuple[float, float, float, float] = (0.87, 0.03, 0.04, 0.06)
    bicycle_prob: float = 0.5  # parked bicycles near a building front, per lot
    # a group of 1-4 bicycles across the sidewalk (rack), per 20 m of sidewalk; 0 = none (the default world,
    # tuned to real seq 00, which holds no bicycle); configs/sim/seg_rich.yaml raises it for segmentor training
    sidewalk_bicycle_prob: float = 0.0
    sign_back_metal: bool = False  # the back of a sign plate is bare metal (real seq-00 signs: median 0.31, q90 0.75)


@dataclass
class AgentConfig:
    """Moving agents per 100 m of ego route, their speeds (m/s) and the ego motion."""

    cars_per_100m: float = 2.0
    trucks_per_100m: float = 0.15
    vans_per_100m: float = 0.15
    pedestrians_per_100m: float = 3.0
    bicyclists_per_100m: float = 1.0
    motorcyclists_per_100m: float = 0.6
    car_speed: tuple[float, float] = (5.0, 12.0)
    pedestrian_speed: tuple[float, float] = (0.9, 1.7)
    bicyclist_speed: tuple[float, float] = (3.0, 7.0)
    motorcyclist_speed: tuple[float, float] = (6.0, 13.0)
    standing_person_prob: float = 0.2  # a pedestrian that does not walk (raw 30 person instead of 254)
    ego_speed: tuple[float, float] = (5.0, 12.0)
    ego_turn_speed: float = 5.0
    ego_accel: float = 1.5  # m/s^2
    ego_turn_prob: float = 0.4  # turn left/right at an intersection instead of going straight
    ego_lateral_jitter: float = 0.15  # m, slow wander within the lane
    # cross slope of the ego lane down to the right curb (road camber, ~2.5 %): the car rolls right, so the flat
    # world reads higher on the right and lower on the left (real seq-00 frame 0: ground at 4.7 m is 0.17 m
    # higher on the right, 0.15 m lower on the left)
    lane_camber: float = 0.025
    ego_center_bias: float = 0.4  # on one-lane-per-direction streets, drive this share closer to the centre
    # m further towards the centre line where a parking strip lines the right of a one-lane street: parked cars
    # passed at ~3 m put 0.86 % of the simulated returns at 3-4 m (real seq 00: 0.09 %, its parked cars are
    # across the street at 7-9 m); proxy range JS over 8 seeds x 8 places x 5 frames 0.1067 -> 0.1005
    ego_parked_clearance: float = 0.8
    # m of route an agent plans beyond its drive in the sequence; a route needs 3 crossings, so long blocks
    # (arterials) need more to keep their traffic
    agent_route_extra: float = 100.0


@dataclass
class LidarConfig:
    """Ray casting and measurement model: sensor mount, noise, drop, intensity."""

    sensor_height: float = 1.80  # KITTI spec 1.73 m; the real seq-00 road plane fits z = -1.80 m in the sensor frame
    # azimuth steps per ring; None: 2083 for hdl64 (HDL-64E at 10 Hz, 0.1728 deg; the real scans show ~2000
    # returns per ring), 1085 for hdl32 (nuScenes ~34k points / 32 rings), else 2 x the sensor's image width
    azimuth_steps: int | None = None
    azimuth_start_deg: float = 0.0  # KITTI rings start facing forward and sweep counter-clockwise
    elevation_jitter_deg: float = 0.03  # per-ring random offset (calibration scatter)
    # lasers sit above the velodyne origin: real KITTI rings read ~0.6 deg higher at 10 m than at 50 m,
    # i.e. an offset of ~0.12 m (seq-00 frame 0); beam angles are corrected so ring medians stay as measured
    laser_offset: tuple[float, float] = (
        0.12,
        0.03,
    )  # m, mean and std of the per-laser vertical origin offset
    mount_tilt_deg: float = 0.3  # std of the per-sequence sensor pitch/roll
    # hdl64 only: the real ground returns of the lowest rings sit higher than their table medians (ring 62
    # hits the road at 4.9 m, i.e. -22.8 deg, table -23.21 deg; seq-00 frame 0): raise rings 57..63 by up to
    bottom_ring_raise_deg: float = 0.45
    azimuth_jitter_deg: float = 0.05  # per-ring random offset
    range_noise: float = 0.015  # m, Gaussian, along the ray
    random_drop: float = 0.004
    grazing_cos: float = 0.03  # |cos incidence| below this: the return is lost with growing probability
    ego_mask: bool = True  # remove rays that hit the ego car body (measured from the real lower rings)
    intensity_incidence_exp: float = 0.5  # g(c) = min(c / incidence_ref, 1) ** exp
    incidence_ref: float = 0.15
    falloff_start: float = 20.0  # m, intensity falls exp(-(r - start) / scale) beyond
    falloff_scale: float = 25.0
    intensity_noise: float = 0.04
    zero_threshold: tuple[float, float] = (0.02, 0.10)  # weak returns read 0 (threshold drawn per point)
    intensity_step: float = 0.01  # KITTI remission is quantised to 0.01
    # returns farther than this read raw 0 (unlabeled): the real seq-00 labels stop at ~50 m (every return beyond
    # 50 m is unlabeled, 1.7 % of a scan); None labels everything
    label_range: float | None = 50.0
    # --- measured sensor and surface model (raycast.py, surfaces.py), fitted to the real seq-00 frames with
    # `u4d sim-report` (per-class remission histograms, range roughness, mixed pixels); off in the default world
    surface_model: Literal["basic", "measured"] = "basic"  # measured: per-material remission gain and range scatter
    ring_gain_spread: float = 0.0  # std of the log remission gain of each laser (HDL-64E lasers differ by ~10 %)
    speckle: float = 0.0  # std of the log remission of each return (mean-preserving)
    range_noise_per_m: float = 0.0  # m of range noise std added per metre of range
    dark_drop: float = 0.0  # returns with a signal below dark_level are lost with up to this probability
    dark_level: float = 0.03  # signal (remission before noise) below which dark returns start to be lost
    mixed_pixel_prob: float = 0.0  # a return at a depth edge (> mixed_pixel_jump) reads a range between both sides
    mixed_pixel_jump: float = 0.5  # m


@dataclass
class StreetTypeWeights:
    """Weight of each street type (u4d_aug.data.sim.scenes); every place (sequence) draws one by its seed."""

    residential: float = 1.0  # the SemanticKITTI seq-00 layout the defaults are tuned to
    arterial: float = 0.0  # wide multi-lane roads, medians, taller buildings, more traffic
    intersection: float = 0.0  # short blocks: many crossings with crosswalks, traffic lights and turns
    park: float = 0.0  # park-side roads: lawn strips between road and sidewalk, park blocks
    parking: float = 0.0  # parking lots, driveways and low kerbs
    green: float = 0.0  # dense vegetation: hedges, gardens, many trees
    plaza: float = 0.0  # small paved squares with people, benches, planters

    def __post_init__(self) -> None:
        names = [f.name for f in fields(self)]
        check_positive(self, *names, allow_zero=True, prefix="street_types.")
        if sum(getattr(self, name) for name in names) <= 0:
            raise InputError(f"key 'street_types': the weights sum to 0; give one of {', '.join(names)} a weight > 0")


@dataclass
class SimConfig:
    """The whole simulated world; `simulate()` saves the resolved copy in manifest.json."""

    street: StreetConfig = field(default_factory=StreetConfig)
    lots: LotConfig = field(default_factory=LotConfig)
    objects: StreetObjectConfig = field(default_factory=StreetObjectConfig)
    agents: AgentConfig = field(default_factory=AgentConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    street_types: StreetTypeWeights = field(default_factory=StreetTypeWeights)
    view_radius: float = 95.0  # m, world is built within this distance of the ego route
    frame_rate: float = 10.0  # Hz

    def __post_init__(self) -> None:
        check_finite_config(self)
        check_positive(self, "view_radius", "frame_rate")
        check_positive(
            self,
            "lidar.ring_gain_spread",
            "lidar.speckle",
            "lidar.range_noise_per_m",
            "lidar.dark_drop",
            "lidar.dark_level",
            "lidar.mixed_pixel_prob",
            "lidar.mixed_pixel_jump",
            "street.median_terrain_prob",
            "street.signal_prob",
            "street.roundabout_prob",
            "lots.park_block_prob",
            "lots.plaza_block_prob",
            "lots.parking_block_prob",
            "lots.driveway_prob",
            allow_zero=True,
        )
        blocks = self.lots.park_block_prob + self.lots.plaza_block_prob + self.lots.parking_block_prob
        if blocks > 1.0:
            raise InputError(f"keys 'lots.park/plaza/parking_block_prob' must sum to <= 1, got {blocks:g}")
        if not 1 <= self.street.main_lanes[0] <= self.street.main_lanes[1]:
            raise InputError(
                f"key 'street.main_lanes' must be (low, high) with 1 <= low <= high, got {self.street.main_lanes}"
            )
