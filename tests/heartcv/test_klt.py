"""heartcv.klt: template Lucas–Kanade on an analytic band-limited texture shifted by an exact sub-pixel
translation; occluded points (flat or foreign texture) are rejected, true tracks pass the forward–backward check."""

import numpy as np
import pytest

from heartcv.klt import LKParams, template_patches, track_from_template

SHIFT = np.array([3.3, -1.7])


def _texture(shape=(160, 200), seed=11, n=40):
    """The analytic image f(x, y): a sum of random sinusoids (wavelengths 8..24 px), sampled exactly anywhere."""
    rng = np.random.default_rng(seed)
    lam = rng.uniform(8.0, 24.0, n)
    ang = rng.uniform(0, np.pi, n)
    k = 2 * np.pi / lam[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    phase = rng.uniform(0, 2 * np.pi, n)
    amp = 70.0 / np.sqrt(n)

    def render(shift=(0.0, 0.0)):
        """uint8 image of f(p - shift): the texture moved by ``shift`` pixels."""
        yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
        x, y = xx - shift[0], yy - shift[1]
        val = 128 + amp * np.cos(x[..., None] * k[:, 0] + y[..., None] * k[:, 1] + phase).sum(axis=-1)
        return np.clip(np.rint(val), 0, 255).astype(np.uint8)

    return render


@pytest.fixture(scope="module")
def images():
    render = _texture()
    return render(), render(SHIFT)


def _points():
    xs, ys = np.meshgrid(np.linspace(40, 160, 4), np.linspace(40, 120, 3))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def test_recovers_an_exact_subpixel_translation(images):
    a, b = images
    p = LKParams()
    uv0 = _points()
    uv, ok, fb, score = track_from_template(a, b, uv0, template_patches(a, uv0, p), uv0, p)
    assert ok.all()
    err = np.linalg.norm(uv - (uv0 + SHIFT), axis=1)
    assert err.max() < 0.02                                # uint8 rounding of the images is the only error
    assert fb.max() < 0.05 and (score > 0.99).all()
    # starting from the true position or with no guess (NaN: the template position) gives the same answer
    uv2, ok2, _, _ = track_from_template(a, b, uv0, template_patches(a, uv0, p), np.full_like(uv0, np.nan), p)
    assert ok2.all() and np.abs(uv2 - uv).max() < 0.01


@pytest.mark.parametrize("cover", ["flat", "foreign texture"])
def test_occluded_points_are_rejected(images, cover):
    a, b = images
    p = LKParams()
    uv0 = _points()
    hidden = [1, 6, 10]
    b = b.copy()
    other = _texture(seed=99)()
    for i in hidden:
        x, y = np.rint(uv0[i] + SHIFT).astype(int)
        r = 17                                              # the LK window (21) and the NCC patch (15) covered
        b[y - r:y + r + 1, x - r:x + r + 1] = 128 if cover == "flat" else other[y - r:y + r + 1, x - r:x + r + 1]
    uv, ok, fb, score = track_from_template(a, b, uv0, template_patches(a, uv0, p), uv0, p)
    assert not ok[hidden].any() and np.isnan(uv[hidden]).all()
    visible = np.setdiff1d(np.arange(len(uv0)), hidden)
    assert ok[visible].all()
    assert np.linalg.norm(uv[visible] - (uv0[visible] + SHIFT), axis=1).max() < 0.02


def test_forward_backward_check_is_applied():
    """True tracks have a tiny forward-backward error; a threshold below it rejects exactly the tracks above it."""
    render = _texture()
    a, b = render(), render(SHIFT)
    uv0 = _points()
    p = LKParams()
    _, ok, fb, _ = track_from_template(a, b, uv0, template_patches(a, uv0, p), uv0, p)
    assert ok.all() and fb.max() < 0.05
    strict = LKParams(fb_max_px=float(np.median(fb)) * 0.999)
    _, ok2, fb2, _ = track_from_template(a, b, uv0, template_patches(a, uv0, strict), uv0, strict)
    assert np.array_equal(fb2, fb) and np.array_equal(ok2, fb <= strict.fb_max_px)
    assert 0 < ok2.sum() < len(uv0)


def test_empty_input_and_parameter_checks(images):
    a, b = images
    uv, ok, fb, score = track_from_template(a, b, np.zeros((0, 2)), np.zeros((0, 225)), np.zeros((0, 2)), LKParams())
    assert uv.shape == (0, 2) and ok.shape == (0,) and fb.shape == (0,) and score.shape == (0,)
    with pytest.raises(ValueError, match="odd"):
        LKParams(window=20)
    with pytest.raises(ValueError, match="levels"):
        LKParams(levels=7)
    assert template_patches(a, _points(), LKParams(ncc_radius=3)).shape == (12, 49)
