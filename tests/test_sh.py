"""SH basis: 3DGS constants and signs, orthonormality, an independent scipy evaluation."""

import numpy as np
import pytest
import scipy.special

from gscodec_shac import sh, sh_index
from gscodec_shac.geometry import fibonacci_sphere


def scipy_real_sh(l, m, directions):
    """Real SH from scipy's complex Y_l^m (Condon-Shortley phase included)."""
    theta = np.arccos(np.clip(directions[:, 2], -1, 1))
    phi = np.arctan2(directions[:, 1], directions[:, 0])
    y = scipy.special.sph_harm_y(l, abs(m), theta, phi)
    if m < 0:
        return np.sqrt(2) * y.imag
    if m == 0:
        return y.real
    return np.sqrt(2) * y.real


def test_basis_matches_independent_scipy_evaluation_up_to_degree_4():
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(300, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    basis = sh.sh_basis(dirs, 4)
    for k in range(25):
        l, m = sh_index.degree_order(k)
        np.testing.assert_allclose(basis[:, k], scipy_real_sh(l, m, dirs), atol=1e-12, err_msg=f"l={l} m={m}")


def test_basis_is_orthonormal_on_the_sphere():
    dirs = fibonacci_sphere(20_000)
    basis = sh.sh_basis(dirs, 4)
    gram = basis.T @ basis * (4 * np.pi / len(dirs))
    np.testing.assert_allclose(gram, np.eye(25), atol=2e-3)


def test_reference_signs_of_degree_one():
    # 3DGS: result = C0*h0 - C1*y*h1 + C1*z*h2 - C1*x*h3
    basis = sh.sh_basis(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), 1)
    np.testing.assert_allclose(basis[0, 1:], [0, 0, -sh.C1], atol=1e-15)
    np.testing.assert_allclose(basis[1, 1:], [-sh.C1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(basis[2, 1:], [0, sh.C1, 0], atol=1e-15)


def test_colour_offset_and_clamp():
    coeffs = np.zeros((2, 16, 3))
    coeffs[0, 0] = sh.rgb_to_sh_dc(np.array([0.2, 0.4, 0.9]))
    coeffs[1, 0] = -10.0  # far below zero: clamped
    colour = sh.eval_sh(coeffs, np.array([[0, 0, 1.0], [1.0, 0, 0]]))
    np.testing.assert_allclose(colour[0], [0.2, 0.4, 0.9], atol=1e-12)
    np.testing.assert_array_equal(colour[1], 0.0)
    assert sh.eval_sh(coeffs, np.array([[0, 0, 1.0], [1.0, 0, 0]]), clamp=False)[1, 0] < 0


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_fit_recovers_coefficients(degree):
    rng = np.random.default_rng(degree)
    k = (degree + 1) ** 2
    truth = rng.normal(size=(7, k, 3))
    dirs = fibonacci_sphere(400)
    values = np.einsum("sk,nkc->nsc", sh.sh_basis(dirs, degree), truth) + 0.5
    np.testing.assert_allclose(sh.fit_sh(dirs, values, degree), truth, atol=1e-9)
