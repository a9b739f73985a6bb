"""Figures a person looks at: dark deep-sea frames are brightened for display, the same on both sides."""
import numpy as np

from uw_sil.viz import MAX_DISPLAY_GAIN, display_gain, gain_words


def test_dark_frame_is_brightened_by_a_power_of_two_that_does_not_clip_it():
    rng = np.random.default_rng(0)
    dark = rng.uniform(0.0, 0.06, (60, 80, 3))          # a lamp-lit panel at a few to 15 grey levels
    g = display_gain(dark)
    assert g == 8, g                                     # 0.06 * 8 = 0.48 <= 0.7 < 0.06 * 16
    assert np.percentile(g * dark, 99.5) <= 0.7
    assert gain_words(g) == ", shown ×8"


def test_bright_frame_is_shown_as_it_is_and_black_gets_the_largest_gain():
    bright = np.full((10, 10, 3), 0.5)
    assert display_gain(bright) == 1 and gain_words(1) == ""
    assert display_gain(np.full((10, 10, 3), 0.9)) == 1          # never darkened
    assert display_gain(np.zeros((10, 10, 3))) == MAX_DISPLAY_GAIN
    assert display_gain(np.full((10, 10), 1e-5)) == MAX_DISPLAY_GAIN
