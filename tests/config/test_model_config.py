"""Model configs: every kind builds, round-trips through to_config(), and bad keys fail."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from invglare.aperture.camera import CameraAperture
from invglare.aperture.eye import EyeAperture
from invglare.config.model import build_model
from invglare.errors import ConfigError
from invglare.files.toml import load_toml
from invglare.models.aperture_psf import AperturePSF
from invglare.models.kakimoto import KakimotoGlare

EYE = {
    "model": {
        "kind": "eye",
        "aperture_npix": 64,
        "eye": {
            "seed": 3,
            "pupil": {"diameter_mm": 3.0},
            "lids": {"upper_opening_mm": 1.3},
            "lashes_upper": {"count": 12, "length_mm": 2.0, "thickness_mm": 0.06},
        },
    },
    "output": {"npix": 64},
    "spectrum": {"wavelengths_nm": 550},
}

def dft_psf(field, pitch_mm: float, wavelength_nm: float, theta_rad) -> np.ndarray:
    """The fraction of the power through the aperture per output pixel, by a direct DFT.

    ``I = |sum f exp(-2 pi i (x theta_x + y theta_y) / lambda)|² pitch² dtheta² /
    (lambda² sum |f|)`` (float64) at the angles `theta_rad` (pixel centres, spacing dtheta),
    per unit power through the aperture, its open area ``sum |f| pitch²``. At the Nyquist
    spacing ``dtheta = lambda / (2 n pitch)`` over ``2n x 2n`` pixels the sum is exactly
    the raster's own power over that, ``sum |f|² / sum |f|`` (Parseval of the ``2n``-point
    DFT); over fewer pixels, the power they hold.
    """
    field = np.asarray(field, dtype=np.float64)
    n = field.shape[0]
    x_mm = (np.arange(n) - n // 2) * pitch_mm
    theta = np.asarray(theta_rad, dtype=np.float64)
    lam_mm = wavelength_nm * 1e-6
    kernel = np.exp(-2j * np.pi * np.outer(theta, x_mm) / lam_mm)
    amplitude = kernel @ field @ kernel.T
    dtheta = theta[1] - theta[0]
    return np.abs(amplitude) ** 2 * pitch_mm**2 * dtheta**2 / (lam_mm**2 * np.sum(np.abs(field)))


def expected_psf_sums(model) -> np.ndarray:
    """The power a raster model's output pixels hold, per wavelength, by `dft_psf`."""
    prop = model.propagator
    field = np.asarray(model.field())
    pitch = float(prop.grid.pitch_mm)
    theta = np.asarray(prop.output.coords_rad(), dtype=np.float64)
    sums = []
    for lam in model.wavelengths_nm:
        # Parseval first: the whole plane at the Nyquist spacing holds the raster's power.
        n = field.shape[0]
        nyquist = (np.arange(2 * n) - n) * lam * 1e-6 / (2 * n * pitch)
        f64 = np.abs(field.astype(np.float64))
        raster_power = np.sum(f64**2) / np.sum(f64)
        assert dft_psf(field, pitch, lam, nyquist).sum() == pytest.approx(raster_power, rel=1e-12)
        sums.append(dft_psf(field, pitch, lam, theta).sum())
    return np.asarray(sums)


CAMERA = {
    "model": {
        "kind": "camera",
        "aperture_npix": 64,
        "obstacle_distance_mm": 5.0,
        "colour": "paper_rgb",
        "camera": {
            "diaphragm": {"n_blades": 6, "f_number": 8.0, "focal_length_mm": 50.0},
            "cross_screen": {"angles_deg": [0.0, 60.0], "spacing_mm": 0.4, "duty_cycle": 0.1},
        },
    },
    "output": {"npix": 64},
}


def test_eye_config_builds_a_kakimoto_model_with_eye_defaults():
    model = build_model(EYE)
    assert isinstance(model, KakimotoGlare)
    assert isinstance(model.aperture, EyeAperture)
    # Eye defaults: 17 mm focal length, lashes 8 mm in front of the pupil, fixed mask.
    assert float(model.propagator.focal_length_mm) == 17.0
    assert float(model.obstacle_distance_mm) == 8.0
    assert model.masking == "fixed"
    psf = np.asarray(model())
    assert psf.shape == (64, 64)
    assert np.all(np.isfinite(psf))
    # Per unit power through the aperture; the 64 px crop of the 128 px FFT holds the power
    # of its pixels (0.955 here: the lashes' and cells' edges send some beyond the grid;
    # the model agrees to 1.5e-6, float32), derived by a direct DFT of the model's field.
    assert model.propagator.method == "fft" and model.propagator.fft_npix == 128
    expected = expected_psf_sums(model)
    assert 0.9 < expected[0] < 0.999
    assert psf.sum() == pytest.approx(expected[0], rel=2e-5)


def test_camera_config_takes_the_diaphragm_focal_length_and_paper_rgb():
    model = build_model(CAMERA)
    assert isinstance(model.aperture, CameraAperture)
    assert float(model.propagator.focal_length_mm) == 50.0
    np.testing.assert_allclose(model.spectrum.wavelengths_nm, [680.0, 530.0, 460.0])
    psf = np.asarray(model())
    assert psf.shape == (64, 64, 3)
    # paper_rgb: each channel is a monochromatic PSF per unit power through the aperture,
    # of which the output pixels hold what a direct DFT of the model's field at that
    # wavelength puts there (0.789, 0.792, 0.799: the filter's many sharp lines on a
    # 64-sample raster send a fifth beyond the grid; the model agrees to 6e-7, float32).
    expected = expected_psf_sums(model)
    assert np.all((0.75 < expected) & (expected < 0.999))
    np.testing.assert_allclose(psf.sum(axis=(0, 1)), expected, rtol=2e-5)


@pytest.mark.parametrize("config", [EYE, CAMERA], ids=["eye", "camera"])
def test_kakimoto_configs_round_trip_exactly(config):
    model = build_model(config)
    again = build_model(model.to_config())
    np.testing.assert_array_equal(np.asarray(again()), np.asarray(model()))
    assert again.to_config() == model.to_config()


def test_bundled_eye_example_round_trips():
    model = build_model(load_toml("examples/eye_daylight.toml"), npix=64)
    assert build_model(model.to_config()).to_config() == model.to_config()


def test_aperture_kind_still_needs_shapes_and_rejects_eye_keys():
    config = copy.deepcopy(EYE)
    config["model"]["kind"] = "aperture"
    config["model"]["focal_length_mm"] = 17.0
    with pytest.raises(ConfigError, match="shapes"):
        build_model(config)
    config["model"]["shapes"] = [{"kind": "disk", "diameter_mm": 3.0}]
    with pytest.raises(ConfigError, match="unknown key 'eye'"):
        build_model(config)
    del config["model"]["eye"]
    assert isinstance(build_model(config), AperturePSF)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda c: c["model"].pop("eye"), "needs the key 'eye'"),
        (lambda c: c["model"].update(masking="sliding"), "masking = 'sliding' is not one of"),
        (lambda c: c["model"].update(colour="cmyk"), "colour = 'cmyk' is not one of"),
        (lambda c: c["model"].update(shapes=[]), "unknown key 'shapes'"),
        (lambda c: c["model"]["eye"].update(iris=1), "unknown key 'iris'"),
        (lambda c: c["model"].update(kind="telescope"), "valid kinds: aperture, eye, camera"),
    ],
)
def test_bad_kakimoto_configs_name_the_key(edit, match):
    config = copy.deepcopy(EYE)
    edit(config)
    with pytest.raises(ConfigError, match=match):
        build_model(config)


def test_veiling_kind_builds_through_the_model_config_and_round_trips():
    config = load_toml("examples/veiling_ghosts.toml")
    model = build_model(config, base_dir="examples")
    image = np.asarray(model((1.0, 0.5)))
    assert np.all(np.isfinite(image)) and image.max() > 0
    again = build_model(model.to_config(), base_dir="examples")
    np.testing.assert_array_equal(np.asarray(again((1.0, 0.5))), image)


def test_psf_command_reports_the_veiling_glare_index(tmp_path):
    from typer.testing import CliRunner

    from invglare.cli import app
    from invglare.files.exr import read_exr

    out = tmp_path / "veil.exr"
    result = CliRunner().invoke(app, ["psf", "examples/veiling_ghosts.toml", "--out", str(out)])
    assert result.exit_code == 0, result.output
    header = read_exr(out).attrs
    assert 0.0 < header["veilingGlareIndex"] < 1.0
    assert header["vgiSpotRadiusDeg"] == 0.5


@pytest.mark.parametrize("reader", ["eye", "camera"])
def test_image_tables_of_eyes_and_cameras_take_their_default_roles(reader, tmp_path):
    """``obstacle_image`` blocks and ``pupil_image`` lets light through unless the table
    says otherwise, in an eye and a camera alike; a ``kind`` there is refused by name."""
    from invglare.config.camera import camera_from_config
    from invglare.config.eye import eye_from_config
    from invglare.files.images import write_png

    write_png(tmp_path / "mask.png", np.eye(16))
    build = eye_from_config if reader == "eye" else camera_from_config
    base = (
        {"pupil": {"diameter_mm": 3.0}}
        if reader == "eye"
        else {"diaphragm": {"n_blades": 6, "f_number": 8.0, "focal_length_mm": 50.0}}
    )
    image = {"path": "mask.png", "width_mm": 4.0}
    built = build({**base, "obstacle_image": image, "pupil_image": image}, reader, tmp_path)
    assert (built.obstacle_image.role, built.pupil_image.role) == ("block", "open")
    swapped = build({**base, "obstacle_image": {**image, "role": "open"}}, reader, tmp_path)
    assert swapped.obstacle_image.role == "open" and swapped.pupil_image is None
    with pytest.raises(ConfigError, match=rf"{reader}\.pupil_image is an image: drop its key"):
        build({**base, "pupil_image": {**image, "kind": "image"}}, reader, tmp_path)
