"""theta = (FSIMc + theta_2) / 2 against cached references, batches and K frames."""

import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import gaussian_filter

from datapaths import TEST_DATA
from uw_sil.metrics.fsim import fsim
from uw_sil.metrics.histsim import hsv_histogram_similarity
from uw_sil.metrics.theta import ThetaReference, ThetaScores, mean_theta

UW = TEST_DATA / "real_underwater"


def _img(name):
    return np.array(Image.open(UW / name))


@pytest.fixture(scope="module")
def frames():
    """Two real 256x256 frames and, for each, 4 candidates of increasing blur + noise."""
    out = []
    rng = np.random.default_rng(0)
    for name in ("euvp_funiegan_testA/1.jpg", "euvp_funiegan_testA/16.jpg"):
        ref = _img(name)
        x = ref.astype(np.float32)
        cands = np.stack(
            [np.clip(gaussian_filter(x, (s, s, 0)) + rng.normal(0, 2 + 4 * s, x.shape), 0, 255) for s in (0.3, 0.8, 1.6, 3.0)]
        ).astype(np.float32)
        out.append((ref, cands))
    return out


def test_components_match_the_standalone_functions(frames):
    ref, cands = frames[0]
    scores = ThetaReference(ref).evaluate(cands)
    assert isinstance(scores, ThetaScores) and scores.theta.shape == (4,)
    np.testing.assert_array_equal(scores.theta, (scores.theta1 + scores.theta2) / 2)
    np.testing.assert_allclose(scores.theta1, [fsim(ref, c).fsimc for c in cands], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(scores.theta2, [hsv_histogram_similarity(ref, c) for c in cands])
    # float64 working precision reproduces the faithful port to rounding
    t64 = ThetaReference(ref, dtype=np.float64).evaluate(cands[:1]).theta1
    assert t64[0] == pytest.approx(fsim(ref, cands[0]).fsimc, abs=1e-12)


def test_batch_equals_one_at_a_time(frames):
    ref, cands = frames[1]
    tref = ThetaReference(ref)
    batch = tref.evaluate(cands)
    for k in range(cands.shape[0]):
        single = tref.evaluate(cands[k])
        assert single.theta[0] == batch.theta[k]
        assert single.theta1[0] == batch.theta1[k] and single.theta2[0] == batch.theta2[k]
    reordered = tref.score(cands[::-1])
    np.testing.assert_array_equal(reordered, batch.theta[::-1])


def test_theta_properties(frames):
    ref, cands = frames[0]
    tref = ThetaReference(ref)
    same = tref.evaluate(ref.astype(np.float32))
    assert same.theta2[0] == 1.0 and same.theta1[0] == pytest.approx(1.0, abs=1e-6)
    theta = tref.score(cands)
    assert np.all((theta > 0) & (theta < 1))
    assert np.all(np.diff(theta) < 0)  # more blur and noise -> lower theta
    assert tref.score(ref)[0] == pytest.approx(1.0, abs=1e-6)  # uint8 candidates accepted


def test_channels_and_mask_are_passed_on(frames):
    ref, cands = frames[0]
    v_only = ThetaReference(ref, channels="V").evaluate(cands)
    np.testing.assert_array_equal(v_only.theta2, [hsv_histogram_similarity(ref, c, channels="V") for c in cands])
    assert ThetaReference(ref, channels="v").channels == "V"
    full = np.ones(ref.shape[:2], bool)
    np.testing.assert_array_equal(ThetaReference(ref, mask=full).score(cands), ThetaReference(ref).score(cands))
    half = full.copy()
    half[:, 128:] = False
    assert not np.array_equal(ThetaReference(ref, mask=half).score(cands), ThetaReference(ref).score(cands))


def test_hist_masks_affect_theta2_only_and_average(frames):
    ref, cands = frames[0]
    left = np.zeros(ref.shape[:2], bool)
    left[:, :100] = True
    plain = ThetaReference(ref).evaluate(cands)
    one = ThetaReference(ref, hist_mask=left).evaluate(cands)
    np.testing.assert_array_equal(one.theta1, plain.theta1)
    np.testing.assert_array_equal(one.theta2, [hsv_histogram_similarity(ref, c, mask=left) for c in cands])
    two = ThetaReference(ref, hist_mask=[left, ~left]).evaluate(cands)
    right = [hsv_histogram_similarity(ref, c, mask=~left) for c in cands]
    np.testing.assert_allclose(two.theta2, (one.theta2 + np.array(right)) / 2, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="empty"):
        ThetaReference(ref, hist_mask=[])


def test_mean_theta_over_frames(frames):
    refs = [ThetaReference(r) for r, _ in frames]
    stacks = [c for _, c in frames]
    want = (refs[0].score(stacks[0]) + refs[1].score(stacks[1])) / 2
    np.testing.assert_allclose(mean_theta(refs, stacks), want, rtol=0, atol=1e-15)
    # raw arrays are accepted too (reference work redone per call)
    np.testing.assert_allclose(mean_theta([r for r, _ in frames], stacks), want, rtol=0, atol=1e-15)


def test_bad_input(frames):
    ref, cands = frames[0]
    tref = ThetaReference(ref)
    with pytest.raises(ValueError, match="shape"):
        tref.score(cands[:, :100])
    with pytest.raises(ValueError, match="empty"):
        tref.score(cands[:0])
    with pytest.raises(TypeError, match="numpy array"):
        tref.score(cands.tolist())
    bad = cands.copy()
    bad[2, 5, 5, 1] = np.nan
    with pytest.raises(ValueError, match=r"candidates\[2\] contains NaN"):
        tref.score(bad)
    with pytest.raises(ValueError, match="RGB"):
        ThetaReference(ref[..., 0])
    with pytest.raises(ValueError, match="2 references but 1"):
        mean_theta([tref, tref], [cands])
    with pytest.raises(ValueError, match="stack 1 has 2 candidates"):
        mean_theta([tref, tref], [cands, cands[:2]])
    with pytest.raises(ValueError, match="empty"):
        mean_theta([], [])


def test_planar_split_and_forked_scores_are_those_of_score_bit_for_bit(frames):
    """The optimizer's inner loop (score_planar, one HSV pass for disjoint histogram masks, a forked reference
    per thread) gives exactly the values of ThetaReference.score; overlapping masks fall back to one pass each."""
    ref, cands = frames[0]
    left = np.zeros(ref.shape[:2], bool)
    left[:, :100] = True
    middle = np.zeros(ref.shape[:2], bool)
    middle[50:200, 60:180] = True
    for masks in ([left, ~left], [left, middle], [left & ~middle, middle]):
        tref = ThetaReference(ref, hist_mask=masks)
        assert (tref._split is not None) == (not np.any(masks[0] & masks[1]))
        want = tref.score(cands)
        separate = [ThetaReference(ref, hist_mask=m).evaluate(cands).theta2 for m in masks]
        np.testing.assert_array_equal(tref.evaluate(cands).theta2, (separate[0] + separate[1]) / 2)
        twin = tref.fork()
        for k, c in enumerate(cands):
            planes = np.ascontiguousarray(np.moveaxis(c, -1, 0)).reshape(3, -1)
            assert tref.score_planar(planes) == want[k]
            assert twin.score_planar(planes) == want[k]
    with pytest.raises(ValueError, match="planes"):
        tref.score_planar(cands[0])
