"""Normals of planar faces from a depth map (uw_sil.sim.normals): the one-sided derivative, exactly."""
import numpy as np

from uw_sil.sim.normals import one_sided_derivative


def test_one_sided_derivative_takes_the_smoother_neighbour_of_the_same_part():
    """The normals' derivative, pixel by pixel as its docstring says: the forward or backward difference within
    the pixel's part, the one of smaller magnitude (forward on a tie), 0 with no neighbour of the same part."""
    rng = np.random.default_rng(7)
    w = rng.normal(size=(9, 11)).astype(np.float32)
    parts = rng.integers(0, 3, size=w.shape).astype(np.uint16)
    parts[4] = 1                              # a row and a column of one part
    parts[:, 5] = 2
    w[4, 1:4] = w[0:3, 5] = (0.0, 1.0, 0.0)   # ties: differences of one magnitude and opposite signs
    for axis in (0, 1):
        got = one_sided_derivative(w, parts, axis)
        a, p = (w, parts) if axis == 1 else (w.T, parts.T)
        want = np.zeros(a.shape, np.float32)
        for i in range(a.shape[0]):
            for j in range(a.shape[1]):
                fwd = a[i, j + 1] - a[i, j] if j + 1 < a.shape[1] and p[i, j + 1] == p[i, j] else None
                bwd = a[i, j] - a[i, j - 1] if j > 0 and p[i, j - 1] == p[i, j] else None
                if fwd is not None and (bwd is None or abs(fwd) <= abs(bwd)):
                    want[i, j] = fwd
                elif bwd is not None:
                    want[i, j] = bwd
        assert got.dtype == np.float32
        assert np.array_equal(got, want if axis == 1 else want.T), axis
