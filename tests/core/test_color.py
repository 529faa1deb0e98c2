"""Colour conversion (mi_nerfpp.core.color): the sRGB curves in NumPy and Dr.Jit, encodings, 8 bits."""
from __future__ import annotations

import numpy as np
import pytest

import mi_nerfpp  # noqa: F401  (libLLVM, variant)
from mi_nerfpp.core import color


def solid(value):
    return np.full((2, 2, 3), value, dtype=np.float32)


@pytest.mark.parametrize('linear, expected', [(0.0, 0), (1.0, 255), (0.5, 188),
                                              (0.0031308, 10), (0.18, 118)])
def test_srgb_oetf_known_values(linear, expected):
    assert np.all(color.to_srgb8(solid(linear)) == expected)


def test_srgb_oetf_continuous_at_cutoff():
    cutoff = color.SRGB_LINEAR_CUTOFF
    below = color.srgb_oetf(np.array(cutoff))
    above = color.srgb_oetf(np.array(np.nextafter(cutoff, 1.0)))
    assert below == pytest.approx(12.92 * cutoff)
    assert above == pytest.approx(below, abs=1e-6)


def test_srgb_oetf_monotonic():
    x = np.linspace(0.0, 1.0, 10001)
    assert np.all(np.diff(color.srgb_oetf(x)) > 0)


def test_to_srgb8_clips_and_handles_nan():
    rgb = np.array([[[-1.0, 2.0, np.nan], [np.inf, -np.inf, 0.25]]])
    assert color.to_srgb8(rgb, 'srgb').tolist() == [[[0, 255, 0], [255, 0, 64]]]
    assert color.to_srgb8(rgb)[0, 0].tolist() == [0, 255, 0]


def test_to_srgb8_srgb_is_identity_encoding():
    assert np.all(color.to_srgb8(solid(0.5), 'srgb') == 128)
    assert color.to_srgb8(solid(0.5)).dtype == np.uint8


def test_to_srgb8_validation():
    with pytest.raises(ValueError, match='color space'):
        color.to_srgb8(solid(0.5), 'acescg')
    with pytest.raises(ValueError, match='H x W x 3'):
        color.to_srgb8(np.zeros((2, 2, 4)))


def test_srgb_eotf_inverts_oetf():
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(color.srgb_eotf(color.srgb_oetf(x)), x, atol=1e-12)
    assert color.srgb_eotf(np.array(color.SRGB_ENCODED_CUTOFF)) == \
        pytest.approx(color.SRGB_LINEAR_CUTOFF, rel=1e-4)


def test_drjit_curves_match_numpy_and_clip():
    import drjit as dr
    import mitsuba as mi
    x = np.linspace(-0.5, 1.5, 2001)
    inside = np.clip(x, 0.0, 1.0)
    encoded = np.array(color.linear_to_srgb(mi.Float(x)))
    decoded = np.array(color.srgb_to_linear(mi.Float(x)))
    np.testing.assert_allclose(encoded, color.srgb_oetf(inside), atol=2e-6)
    np.testing.assert_allclose(decoded, color.srgb_eotf(inside), atol=2e-6)
    rgb = color.srgb_to_linear(mi.Color3f(0.5, 0.2, 0.9))
    assert isinstance(rgb, mi.Color3f) and dr.width(rgb) == 1


def test_encode_is_the_training_image_encoding():
    linear = np.array([[[-0.1, 0.18, 1.5]]], dtype=np.float32)
    srgb = color.encode(linear, 'srgb')
    assert srgb.dtype == np.float32
    np.testing.assert_allclose(srgb, color.srgb_oetf(np.clip(linear, 0, 1)), atol=1e-7)
    np.testing.assert_array_equal(color.encode(linear, 'linear'), linear)
    with pytest.raises(ValueError, match="unknown color space 'acescg'"):
        color.encode(linear, 'acescg')


def test_quantize8_clips_rounds_and_zeroes_nan():
    values = np.array([-1.0, 0.0, 0.5 / 255, 1.5 / 255, 0.5, 1.0, 7.0, np.nan, np.inf])
    assert color.quantize8(values).tolist() == [0, 0, 0, 2, 128, 255, 255, 0, 255]
    assert color.quantize8(values).dtype == np.uint8
