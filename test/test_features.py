"""Feature-match counting: every descriptor runs; a warped copy matches, noise does not; determinism."""
import csv

import cv2
import numpy as np
import pytest

from uw_sil.enhance.features import (ALL_DESCRIPTORS, MIN_VERIFIED, MatchResult, draw_matches,
                                     match_features, match_table, table_csv, table_markdown)

SHAPE = (240, 320)


def _shapes(seed=0):
    """Random filled rectangles and discs with mild noise: corners and blobs for every detector."""
    rng = np.random.default_rng(seed)
    img = np.full((*SHAPE, 3), 110, np.uint8)
    for _ in range(120):
        colour = tuple(int(v) for v in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, SHAPE[1])), int(rng.integers(0, SHAPE[0]))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(8, 50)), y + int(rng.integers(8, 50))), colour, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(4, 25)), colour, -1)
    return np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)


def _warp():
    """Rotation by 8 degrees about the centre and a shift of (10, -6) px, as a homography."""
    M = cv2.getRotationMatrix2D((SHAPE[1] / 2, SHAPE[0] / 2), 8, 1.0)
    M[:, 2] += (10, -6)
    return np.vstack([M, [0, 0, 1]])


@pytest.fixture(scope="module")
def pair():
    a = _shapes()
    H = _warp()
    b = cv2.warpPerspective(a, H, SHAPE[::-1], borderMode=cv2.BORDER_REFLECT)
    return a, b, H


def _reprojection_error(Hest, H, pts):
    ph = np.c_[pts.astype(np.float64), np.ones(len(pts))]
    p1, p2 = ph @ Hest.T, ph @ H.T
    return np.abs(p1[:, :2] / p1[:, 2:] - p2[:, :2] / p2[:, 2:]).max()


@pytest.mark.parametrize("descriptor", ALL_DESCRIPTORS)
def test_warped_copy_gives_many_verified_matches(pair, descriptor):
    a, b, H = pair
    r = match_features(a, b, descriptor)
    assert isinstance(r, MatchResult)
    assert r.n_verified >= 12, (r.n_raw, r.n_verified)
    assert r.n_verified >= 0.5 * r.n_raw
    # the verified matches agree with the true warp
    p1, p2 = r.points("verified")
    proj = cv2.perspectiveTransform(p1[None].astype(np.float64), H)[0]
    assert np.median(np.linalg.norm(proj - p2, axis=1)) < 2.0
    assert _reprojection_error(r.homography, H, p1) < 3.0   # where the matches are
    assert (r.distances < 0.25).all()
    np.testing.assert_array_equal(r.verified_matches, r.raw_matches[r.inlier_mask])


@pytest.mark.parametrize("descriptor", ALL_DESCRIPTORS)
def test_noise_gives_no_verified_matches(descriptor):
    n1 = np.random.default_rng(5).integers(0, 256, (*SHAPE, 3), dtype=np.uint8)
    n2 = np.random.default_rng(6).integers(0, 256, (*SHAPE, 3), dtype=np.uint8)
    r = match_features(n1, n2, descriptor)
    assert r.n_verified == 0
    assert r.homography is None


@pytest.mark.parametrize("descriptor", ALL_DESCRIPTORS)
def test_counts_are_deterministic(pair, descriptor):
    a, b, _ = pair
    r1, r2 = match_features(a, b, descriptor), match_features(a, b, descriptor)
    np.testing.assert_array_equal(r1.raw_matches, r2.raw_matches)
    np.testing.assert_array_equal(r1.inlier_mask, r2.inlier_mask)
    np.testing.assert_array_equal(r1.distances, r2.distances)
    assert [k.pt for k in r1.keypoints1] == [k.pt for k in r2.keypoints1]


def test_binary_distances_are_bit_fractions_and_float_ones_unit_l2(pair):
    a, _, _ = pair
    # a frame against itself: every mutual nearest neighbour is the keypoint itself, at distance 0
    for descriptor in ("ORB", "SIFT"):
        r = match_features(a, a, descriptor)
        assert r.n_raw == len(r.keypoints1) > 0
        np.testing.assert_array_equal(r.raw_matches[:, 0], r.raw_matches[:, 1])
        assert r.distances.max() < 1e-5


def test_masks_restrict_keypoints(pair):
    a, b, _ = pair
    mask = np.zeros(SHAPE, np.uint8)
    mask[:, :160] = 1
    for descriptor in ("SIFT", "SURF"):
        r = match_features(a, b, descriptor, mask1=mask)
        assert len(r.keypoints1) > 0
        assert all(k.pt[0] < 161 for k in r.keypoints1)
        assert any(k.pt[0] > 170 for k in r.keypoints2)
    with pytest.raises(ValueError, match="shape"):
        match_features(a, b, "ORB", mask1=np.ones((10, 10)))


def test_inputs_float_grey_and_bad(pair):
    a, b, _ = pair
    r8 = match_features(a, b, "AKAZE")
    rf = match_features(a.astype(np.float32) / 255, b.astype(np.float32) / 255, "AKAZE")
    assert rf.n_verified == r8.n_verified
    grey = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
    assert match_features(grey, cv2.cvtColor(b, cv2.COLOR_RGB2GRAY), "akaze").n_verified == r8.n_verified
    with pytest.raises(ValueError, match="descriptor"):
        match_features(a, b, "FREAK")
    with pytest.raises(ValueError, match="shape"):
        match_features(a[..., :2], b, "ORB")
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        match_features(a.astype(np.float32), b, "ORB")


def test_table_markdown_csv_and_drawing(pair, tmp_path):
    a, b, _ = pair
    noise = np.random.default_rng(1).integers(0, 256, (*SHAPE, 3), dtype=np.uint8)
    rows = match_table({"warped": (a, b), "noise": (a, noise, None, None)}, descriptors=("ORB", "BRIEF", "SURF"))
    assert [(r["pair"], r["descriptor"]) for r in rows] == [
        ("warped", "ORB"), ("warped", "BRIEF"), ("warped", "SURF"),
        ("noise", "ORB"), ("noise", "BRIEF"), ("noise", "SURF")]
    assert rows[0]["verified_matches"] >= MIN_VERIFIED and rows[3]["verified_matches"] == 0
    assert rows[1]["detector"] in ("STAR", "FAST")
    md = table_markdown(rows)
    lines = md.splitlines()
    assert lines[0] == "| pair | ORB | BRIEF | SURF |"
    assert lines[2].startswith(f"| warped | {rows[0]['verified_matches']} ({rows[0]['raw_matches']}) |")
    assert "mahotas" in md and "BRIEF: STAR keypoints" in md or "BRIEF: FAST keypoints" in md
    path = table_csv(rows, tmp_path / "sub" / "table2.csv")
    with open(path, newline="") as fh:
        back = list(csv.DictReader(fh))
    assert len(back) == 6 and back[0]["descriptor"] == "ORB"
    assert int(back[0]["verified_matches"]) == rows[0]["verified_matches"]
    assert sorted(p.name for p in path.parent.iterdir()) == ["table2.csv"]   # no temp file left
    r = match_features(a, b, "ORB")
    pic = draw_matches(a, b, r, max_lines=20)
    assert pic.shape == (SHAPE[0], 2 * SHAPE[1], 3) and pic.dtype == np.uint8
    np.testing.assert_array_equal(draw_matches(a, b, r, max_lines=20), pic)
    assert (pic != np.hstack([a, b])).any()              # lines were drawn
    # a failed write leaves the old file and no temp file
    with pytest.raises(AttributeError):
        table_csv([{"pair": "x", "descriptor": "ORB"}, 5], path)          # 5 is not a row
    assert sorted(p.name for p in path.parent.iterdir()) == ["table2.csv"]
    assert len(list(csv.DictReader(open(path, newline="")))) == 6


def test_public_names_are_sorted_and_lazy():
    import subprocess
    import sys

    import uw_sil.enhance as enhance
    import uw_sil.enhance.dcp as dcp
    import uw_sil.enhance.features as features
    import uw_sil.metrics.uiqm as uiqm

    for module in (enhance, dcp, features, uiqm):
        assert list(module.__all__) == sorted(module.__all__), module.__name__
    for name in enhance.__all__:
        assert getattr(enhance, name) is not None
    assert enhance.match_features is features.match_features and enhance.dehaze_dcp is dcp.dehaze_dcp
    with pytest.raises(AttributeError):
        enhance.no_such_name
    # importing the package alone does not import its submodules (a fresh interpreter)
    code = "import sys, uw_sil.enhance; print(any(k.startswith('uw_sil.enhance.') for k in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
