"""Small model configs for the torch tests: 32 px aperture rasters, 32 px PSFs (fast)."""

from __future__ import annotations

import copy


def eye_config(masking: str = "fixed", npix: int = 32, colour: str | None = None) -> dict:
    """A daylight-like eye: 3 mm pupil, lids, 12 upper lashes, 16 cornea cells, 550 nm."""
    config = {
        "model": {
            "kind": "eye",
            "focal_length_mm": 17.0,
            "obstacle_distance_mm": 8.0,
            "masking": masking,
            "aperture_npix": 32,
            "window_mm": 4.8,
            "method": "mft",
            "eye": {
                "seed": 7,
                "pupil": {"diameter_mm": 3.0},
                "lids": {"upper_opening_mm": 1.2, "lower_opening_mm": 1.4},
                "lashes_upper": {
                    "count": 10.5,
                    "n_max": 12,
                    "thickness_mm": 0.12,
                    "length_mm": 2.5,
                    "root_span_mm": 8.0,
                },
                "particles": [
                    {"region": "cornea", "count": 12.5, "n_max": 16, "radius_mean_mm": 0.05}
                ],
            },
        },
        "output": {"npix": npix, "pixel_scale_deg": 0.005},
        "spectrum": {"wavelengths_nm": 550.0},
    }
    if masking == "position":
        config["model"]["max_light_angle_deg"] = 0.2
    if colour is not None:
        config["model"]["colour"] = colour
        config["spectrum"] = {} if colour == "paper_rgb" else config["spectrum"]
    return config


def camera_config(n_blades: int = 6) -> dict:
    """A 50 mm f/8 lens, `n_blades` blades, a two-way cross screen 20 mm in front, 550 nm."""
    return {
        "model": {
            "kind": "camera",
            "obstacle_distance_mm": 20.0,
            "aperture_npix": 32,
            "window_mm": 8.4,
            "method": "mft",
            "camera": {
                "diaphragm": {"n_blades": n_blades, "f_number": 8.0, "focal_length_mm": 50.0},
                "cross_screen": {"angles_deg": [0.0, 90.0], "spacing_mm": 1.0, "duty_cycle": 0.2},
            },
        },
        "output": {"npix": 32, "pixel_scale_deg": 0.0035},
        "spectrum": {"wavelengths_nm": 550.0},
    }


def copy_of(config: dict) -> dict:
    return copy.deepcopy(config)


def disk_config(npix: int = 32, rgb: bool = False) -> dict:
    """A 4 mm circular pupil, 17 mm focal length, 550 nm, FFT-native output (fastest).

    `rgb`: 450 / 550 / 650 nm integrated to linear RGB (matrix Fourier transforms).
    """
    if rgb:
        config = disk_config(npix)
        config["model"]["method"] = "mft"
        config["output"]["pixel_scale_deg"] = 0.0025
        config["spectrum"] = {"wavelengths_nm": [450.0, 550.0, 650.0]}
        return config
    return {
        "model": {
            "kind": "aperture",
            "focal_length_mm": 17.0,
            "aperture_npix": npix // 2,
            "window_mm": 5.0,
            "shapes": [{"kind": "disk", "diameter_mm": 4.0}],
        },
        "output": {"npix": npix},
        "spectrum": {"wavelengths_nm": 550.0},
    }
