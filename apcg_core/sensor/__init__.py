"""Lidar effects after the ray casting (SPEC section 8): the photon stage of a single-photon
lidar. numpy only. ``load_sensor`` reads a preset or a TOML ``[sensor]`` table (None: the ideal
lidar, no stage); ``photon_cloud`` turns the simulator's sub-ray hits into what the sensor
records; ``reflectivity_of`` gives a catalog type's reflectivity at the sensor's wavelength."""

from .params import (
    IDEAL,
    OUTPUTS,
    PRESET_DIR,
    SensorParams,
    check_sensor,
    load_sensor,
    preset_names,
    sensor_from_table,
)
from .reflectivity import CATEGORY_REFLECTIVITY, reflectivity_of
from .stage import PhotonCells, SubRayHits, photon_cloud, sample_rng, to_cloud

__all__ = ["CATEGORY_REFLECTIVITY", "IDEAL", "OUTPUTS", "PRESET_DIR", "PhotonCells",
           "SensorParams", "SubRayHits", "check_sensor", "load_sensor", "photon_cloud",
           "preset_names", "reflectivity_of", "sample_rng", "sensor_from_table", "to_cloud"]
