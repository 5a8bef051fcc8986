"""The virtual diffuser camera against physics (not against itself)."""

import dataclasses

import numpy as np
import pytest
from skimage.registration import phase_cross_correlation

from psfkit.errors import ConfigurationError
from psfkit.numerics.resample import bin_image
from psfkit.simulate import BenchConfig, VirtualCamera
from psfkit.simulate.psf_patch import translate_pixels
from tests.helpers.optics import fresnel_transfer_anisotropic, propagate


@pytest.fixture(scope="module")
def camera():
    """Binned 4× (270 × 360 pixels of 13.8 µm): fine enough for 0.1-px shift checks."""
    return VirtualCamera(BenchConfig(downsample=4))


def test_energy_is_conserved_and_nothing_wraps_around(camera):
    on_axis = camera.psf_patch((0.0, 0.0))
    # unit-intensity envelope over the aperture → every channel sums to 1 on axis
    np.testing.assert_allclose(on_axis.image.sum(axis=(1, 2)), 1.0, rtol=1e-5)
    field = (7.0, -5.0)
    off_axis = camera.psf_patch(field)
    cos_theta = 1.0 / np.sqrt(1 + np.tan(np.deg2rad(7.0)) ** 2 + np.tan(np.deg2rad(5.0)) ** 2)
    np.testing.assert_allclose(off_axis.image.sum(axis=(1, 2)), cos_theta**4, rtol=1e-5)
    # the block is large enough: its border (where wrapped light would land) stays dark
    for patch in (on_axis, off_axis):
        img = patch.image
        border = img.sum() - img[:, 8:-8, 8:-8].sum()
        assert border < 1e-4 * img.sum()


@pytest.mark.parametrize("field", [(3.0, 0.0), (0.0, -4.0), (5.0, 3.0), (-6.0, 5.0),
                                   (8.0, 0.0)])
def test_off_axis_shift_is_d_tan_theta(camera, field):
    """Registered shift of the simulated PSF vs. −d·tanθ from the geometry (within 0.1 px)."""
    reference = camera.psf((0.0, 0.0))[1]
    moved = camera.psf(field)[1]
    (dv, du), _, _ = phase_cross_correlation(moved, reference, upsample_factor=200,
                                             normalization=None)
    gap_um, pixel_um = 14.6e3, 3.45 * 4
    expected_du = -gap_um * np.tan(np.deg2rad(field[0])) / pixel_um
    expected_dv = -gap_um * np.tan(np.deg2rad(field[1])) / pixel_um
    assert du == pytest.approx(expected_du, abs=0.1)
    assert dv == pytest.approx(expected_dv, abs=0.1)


def test_mirror_symmetry():
    """A mirror-symmetric diffuser gives mirror-image PSFs at +θ and −θ (and a random one
    does not, so the check has teeth)."""
    config = BenchConfig(downsample=8)
    random_cam = VirtualCamera(config)

    def symmetric_surface(y_um, x_um):
        h = random_cam.diffuser.height(y_um, x_um)  # x grid is symmetric about 0
        return 0.5 * (h + h[:, ::-1])

    sym_cam = VirtualCamera(config, surface=symmetric_surface)
    for field in [(6.0, 0.0), (6.0, 3.0)]:
        mirrored = (-field[0], field[1])
        a, b = sym_cam.psf(field), sym_cam.psf(mirrored)[:, :, ::-1]
        assert np.linalg.norm(a - b) / np.linalg.norm(a) < 1e-4
        a, b = random_cam.psf(field), random_cam.psf(mirrored)[:, :, ::-1]
        assert np.linalg.norm(a - b) / np.linalg.norm(a) > 0.3


@pytest.mark.parametrize("field", [(8.0, 0.0), (0.0, 6.0), (7.0, 5.0), (-9.6, -7.0)])
def test_off_axis_psf_is_on_axis_psf_propagated_over_anisotropic_distances(field):
    """With its shift removed, the PSF at θ matches the on-axis field propagated over
    d/cos³θ (tangential) and d/cosθ (sagittal) far better than the on-axis PSF itself."""
    cam = VirtualCamera(BenchConfig(downsample=4, spherical_source=False, source_size_px=0))
    g = 1  # green channel
    off = cam.psf_patch(field, subpixel_shift=False).image[g] / cam.gain(field)
    on = cam.psf_patch((0.0, 0.0), subpixel_shift=False).image[g]
    alpha, beta, gamma = cam.direction_cosines(field)
    d = cam.gap_um
    shape = (cam.y_um.size, cam.x_um.size)
    envelope = cam.envelope((0.0, 0.0), g).astype(np.complex128)

    def propagated(d_t, d_s):
        transfer = fresnel_transfer_anisotropic(shape, cam.sim_pitch_um, cam.wavelengths_um[g],
                                                d_t, d_s, np.arctan2(beta, alpha))
        intensity = bin_image(np.abs(propagate(envelope, transfer)) ** 2, cam.oversample,
                              exact=True)
        return intensity * (on.sum() / intensity.sum())

    def rel(a, b):
        return np.linalg.norm(a - b) / np.linalg.norm(a)

    err_model = rel(off, propagated(d / gamma**3, d / gamma))
    err_plain = rel(off, on)
    err_swapped = rel(off, propagated(d / gamma, d / gamma**3))
    assert err_model < 0.03
    assert err_plain > 5 * err_model
    assert err_swapped > 5 * err_model


def test_same_seed_same_psf_and_other_seed_other_diffuser():
    a = VirtualCamera(BenchConfig(downsample=8, seed=3)).psf((2.0, 1.0))
    b = VirtualCamera(BenchConfig(downsample=8, seed=3)).psf((2.0, 1.0))
    c = VirtualCamera(BenchConfig(downsample=8, seed=4)).psf((2.0, 1.0))
    np.testing.assert_array_equal(a, b)
    assert np.linalg.norm(a - c) > 0.3 * np.linalg.norm(a)


def test_diffuser_is_the_same_object_at_any_sampling():
    """The surface is defined in physical units: two samplings agree where they overlap."""
    coarse = VirtualCamera(BenchConfig(downsample=8))
    fine = VirtualCamera(BenchConfig(downsample=4))
    y = np.linspace(-800.0, 800.0, 33)
    np.testing.assert_allclose(coarse.diffuser.height(y, y), fine.diffuser.height(y, y),
                               rtol=0, atol=1e-9)


@pytest.mark.parametrize("angle_deg", [0.5, 1.0, 2.0])
def test_scattered_light_has_the_requested_diffusion_angle(angle_deg):
    """Angular spectrum of the light leaving the diffuser: its FWHM (from the second moment
    of a Gaussian profile) is the configured diffusion angle, for every wavelength."""
    cam = VirtualCamera(BenchConfig(downsample=4, diffusion_angle_deg=angle_deg,
                                    spherical_source=False))
    for c, lam in enumerate(cam.wavelengths_um):
        spectrum = np.abs(np.fft.fft2(cam.envelope((0.0, 0.0), c))) ** 2
        gx = np.fft.fftfreq(spectrum.shape[1], cam.sim_pitch_um)
        angle = np.rad2deg(np.arcsin(gx * lam))
        marginal = spectrum.sum(axis=0)
        std = np.sqrt(np.sum(marginal * angle**2) / marginal.sum())
        assert 2.3548 * std == pytest.approx(angle_deg, rel=0.06)


def test_config_round_trip_and_validation():
    config = BenchConfig(downsample=2, wavelengths_nm=(530.0,), seed=7)
    assert BenchConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ConfigurationError, match="refractive_index"):
        BenchConfig(refractive_index=0.9)
    with pytest.raises(ConfigurationError, match="downsample"):
        BenchConfig(downsample=0)
    with pytest.raises(ConfigurationError, match="unknown"):
        BenchConfig.from_dict({"gapp_mm": 3})
    with pytest.raises(ConfigurationError, match="surface returned shape"):
        VirtualCamera(BenchConfig(downsample=8), surface=lambda y, x: np.zeros((3, 3)))


def test_mono_camera_has_one_channel():
    cam = VirtualCamera(dataclasses.replace(BenchConfig(downsample=8), wavelengths_nm=(530.0,)))
    assert cam.psf((1.0, 1.0)).shape == (1, 135, 180)
    assert cam.channels == ("L",)


@pytest.mark.parametrize("spherical", [True, False])
def test_torch_optics_match_the_numpy_reference(spherical):
    """float32 torch path vs the float64-phase NumPy path: relative L2 below 1e-4 (measured
    ~5e-7), at the field edge too, and the chief-ray placement identical."""
    config = dataclasses.replace(BenchConfig(downsample=4), spherical_source=spherical)
    numpy_cam = VirtualCamera(config, backend="numpy")
    torch_cam = VirtualCamera(config, backend="torch", device="cpu")
    assert numpy_cam.backend == "numpy" and torch_cam.backend == "torch"
    for field in [(0.0, 0.0), (9.5, -7.0), (-3.3, 5.1)]:
        ref, new = numpy_cam.psf_patch(field), torch_cam.psf_patch(field)
        assert new.offset == ref.offset and new.shift_px == ref.shift_px
        assert np.linalg.norm(new.image - ref.image) / np.linalg.norm(ref.image) < 1e-4
    with pytest.raises(ConfigurationError, match="backend"):
        VirtualCamera(config, backend="jax")


def test_field_free_camera_translates_the_on_axis_psf():
    """Issue 43's field-free bench: every PSF is the on-axis PSF moved by the chief-ray shift
    (−d·tanθ, linear in tanθ), with no vignetting and no change of shape; the default camera
    (same diffuser) does change, so the check has teeth."""
    config = BenchConfig(downsample=8, field_free=True)
    free, varying = VirtualCamera(config), VirtualCamera(BenchConfig(downsample=8))
    on_axis = free.psf_patch((0.0, 0.0)).image
    np.testing.assert_allclose(on_axis, varying.psf_patch((0.0, 0.0)).image, rtol=1e-6)
    pixel_um = 3.45 * 8
    for field in [(6.0, -4.0), (-9.0, 7.0)]:
        assert free.gain(field) == 1.0 and varying.gain(field) < 0.99
        patch = free.psf_patch(field, subpixel_shift=False)
        np.testing.assert_array_equal(patch.image, on_axis)
        assert not np.allclose(varying.psf_patch(field, subpixel_shift=False).image
                               / varying.gain(field), on_axis, rtol=0.05, atol=0.0)
        expected = tuple(-14.6e3 * np.tan(np.deg2rad(f)) / pixel_um for f in field)
        assert free.true_shift_px(field) == pytest.approx(expected, rel=1e-9)
        moved = free.psf_patch(field)
        assert moved.image.sum() == pytest.approx(on_axis.sum(), rel=1e-5)
        # the sub-pixel part is a band-limited translation of the sampled PSF: undone by the
        # opposite one, but for the Nyquist frequencies of the aliased PSF (a real-valued
        # sinusoid at Nyquist cannot move by a fraction of a pixel), 0.5 % of the peak here
        back = translate_pixels(moved.image, (round(expected[0]) - expected[0],
                                              round(expected[1]) - expected[1]))
        np.testing.assert_allclose(back, on_axis, atol=0.01 * on_axis.max())
        assert not np.allclose(moved.image, on_axis, atol=0.01 * on_axis.max())
        centre = free.psf_patch((0.0, 0.0)).offset
        assert (moved.offset[0] - centre[0], moved.offset[1] - centre[1]) == (
            round(expected[1]), round(expected[0]))
    assert BenchConfig.from_dict(config.to_dict()).field_free
