"""Names of groups, datasets and attributes in a hybrid-capture file (spec/hybrid-capture.md)."""

from __future__ import annotations

FRAMES = "frames"
EVENTS = "events"
TRIGGERS = "triggers"
LIGHTS = "lights"
CALIBRATION = "calibration"
GROUND_TRUTH = "ground_truth"
MATERIALS = "materials"
RESULTS = "results"

ROOT_ATTRS = ("format", "format_version", "creator", "creator_version", "created", "description")
FRAME_ATTRS = ("color_order", "bit_depth", "saturation", "black_level", "response")
FRAME_WINDOW = ("t_start_us", "t_end_us")
FRAME_INSTANT = ("light_direction", "light_intensity")
CALIBRATION_ATTRS = ("contrast_pos", "contrast_neg", "refractory_us", "refractory_rule", "camera_model")
SENSOR_MODEL_NAME = "sensor_model"
SENSOR_MODEL_FIGURES = (
    "contrast_sigma", "leak_hz", "shot_noise_hz", "rate_spread_decades", "hot_pixel_fraction", "hot_pixel_hz",
    "full_well_e", "read_noise_e",
)
"""The optional sensor-model attributes of ``/calibration`` (format 1.3, spec §9.2): the model's name,
then its figures, each a real ≥ 0."""
GT_MAPS = ("normal", "mask", "albedo", "depth")
RESULT_ATTRS = ("solver", "options", "seconds", "version", "created")
