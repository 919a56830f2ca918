"""Closed-form starting poses for PnP: EPnP for general point sets, IPPE for planar ones.

Both work on one problem in normalised image coordinates `m = (x/z, y/z)` (undistorted, K
removed) with per-point weights `w` (0 marks padding), have static shapes, and are vmapped by
`jaxreg.camera.pnp`. They are starts for Levenberg-Marquardt, not answers: `jaxreg.camera.pnp`
refines them and explains which it keeps.

* EPnP (Lepetit, Moreno-Noguer, Fua 2009) is linear, works from n = 4 non-coplanar points (a
  DLT on normalised coordinates needs n >= 6), and costs one 12x12 eigendecomposition plus a
  fixed-size Gauss-Newton on four control-point weights. Its three standard approximations
  give three starts. It is ill-posed for coplanar points, hence IPPE beside it.
* IPPE (Collins & Bartoli 2014): a DLT homography maps the plane (the best-fit plane of the
  object points; for a tag its z = 0 plane) to normalised image coordinates; its first-order
  expansion at the centroid determines the 2x2 top-left block of the rotation up to the sign of
  the out-of-plane row, which gives two analytic rotations, each with its least-squares
  translation.

jaxlib 0.10's CPU LAPACK kernels split a large batch over XLA's intra-op thread pool and block a
pool thread until the pieces finish; two such calls running at once on a 2-thread pool can wait
for each other forever (seen with eigh and LU side by side from ~5000 tags up). So the PCAs,
2x2 and 3x3 systems and the four-point homography here are closed form (the planar path makes no
LAPACK call; on XLA's CPU backend a batched `eigh` or `svd` of tiny matrices is also ~10x
slower than the elementwise closed form), and EPnP's calls that would be independent are batched
into one. (An
`optimization_barrier` cannot order the remaining calls: XLA's CPU compiler strips it before
scheduling, the compiled program is byte-identical with or without one.)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxlie import SE3, SO3
from jaxtyping import Array, Float

from jaxreg.camera._pnp_linalg import matmul
from jaxreg.geometry.alignment import align
from jaxreg.geometry.eigen import eigh3

__all__ = ["general_starts", "image_spread", "ippe_candidates", "weighted_pca"]


def weighted_pca(X: Float[Array, "N 3"], w: Float[Array, " N"]):
    """Weighted PCA of the object points: centroid `(3,)`, eigenvalues `(3,)` ascending and
    unit eigenvectors `(3, 3)` as columns, in closed form (elementwise over a vmapped batch)."""
    wsum = jnp.maximum(jnp.sum(w), jnp.finfo(X.dtype).tiny)
    centroid = jnp.sum(w[:, None] * X, axis=0) / wsum
    centred = X - centroid
    entries = jnp.stack(
        [
            jnp.sum(w * centred[:, i] * centred[:, j]) / wsum
            for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
        ]
    )
    evals, evecs = eigh3(entries)
    return centroid, jnp.maximum(evals, 0.0), evecs


def image_spread(m: Float[Array, "N 2"], w: Float[Array, " N"]) -> Float[Array, "2"]:
    """Eigenvalues `(2,)`, ascending, of the weighted scatter of the normalised image points."""
    wsum = jnp.maximum(jnp.sum(w), jnp.finfo(m.dtype).tiny)
    centred = m - jnp.sum(w[:, None] * m, axis=0) / wsum
    x, y = centred[:, 0], centred[:, 1]
    a, b, c = jnp.sum(w * x * x) / wsum, jnp.sum(w * x * y) / wsum, jnp.sum(w * y * y) / wsum
    mean = 0.5 * (a + c)
    big = mean + jnp.sqrt(0.25 * (a - c) ** 2 + b * b)
    # The smaller one as det / big: no cancellation between mean and the square root.
    small = (a * c - b * b) / jnp.where(big > 0, big, 1.0)
    return jnp.maximum(jnp.stack([small, big]), 0.0)


def _null_vector(A: Array) -> Array:
    """The right singular vector of A with the smallest singular value. A is zero-padded to
    be at least square."""
    rows, cols = A.shape
    if rows < cols:
        A = jnp.concatenate([A, jnp.zeros((cols - rows, cols), A.dtype)], axis=0)
    return jnp.linalg.svd(A, full_matrices=False)[2][-1]


def _epnp_kernel(M: Array, count: Array) -> Array:
    """EPnP's four kernel vectors, rows `(4, 12)`: the right singular vectors of M with the
    smallest singular values, smallest first, from the eigenvectors of the 12x12 `M^T M`.

    With 4 or 5 valid points, `12 - 2 count` of them span an exact null space, whose basis a
    solver picks arbitrarily (differently for a zero-padded copy of the same problem), and
    EPnP's linearisations depend on that basis. There the basis is made canonical: the
    eigenvectors of `diag(1, ..., 12)` compressed to the null space. Signs are fixed by the
    largest component, so the kernel, and the starts, depend on the valid rows alone.
    """
    dtype = M.dtype
    _, evecs = jnp.linalg.eigh(M.T @ M)
    V = evecs[:, :4]
    null_dim = jnp.clip(12 - 2 * count, 0, 4)
    index = jnp.arange(4)
    in_null = (index[:, None] < null_dim) & (index[None, :] < null_dim)
    compressed = V.T @ (jnp.arange(1, 13, dtype=dtype)[:, None] * V)  # eigenvalues in [1, 12]
    # Outside the null block: distinct values above 12, so those vectors keep their place.
    _, Q = jnp.linalg.eigh(jnp.where(in_null, compressed, jnp.diag(13.0 + index.astype(dtype))))
    B = (V @ Q).T
    largest = jnp.take_along_axis(B, jnp.argmax(jnp.abs(B), axis=1)[:, None], axis=1)
    return B * jnp.where(largest < 0, -1.0, 1.0)


def _translation_given_rotation(R, X: Array, m: Array, w: Array) -> tuple:
    """Least-squares t for fixed R (rows of scalars) on the algebraic error
    [1 0 -u; 0 1 -v](R X + t) = 0, as three scalars; X `(N, 3)`, m `(N, 2)`, w `(N,)`.

    The normal matrix is `[[W, 0, -Su], [0, W, -Sv], [-Su, -Sv, S(u^2 + v^2)]]` (weighted sums
    over the points), solved by its adjugate."""
    u, v = m[:, 0], m[:, 1]
    Y = [R[i][0] * X[:, 0] + R[i][1] * X[:, 1] + R[i][2] * X[:, 2] for i in range(3)]
    ru, rv = w * (u * Y[2] - Y[0]), w * (v * Y[2] - Y[1])  # weighted right-hand sides
    sw, su, sv = jnp.sum(w), jnp.sum(w * u), jnp.sum(w * v)
    suv = jnp.sum(w * (u * u + v * v))
    b = (jnp.sum(ru), jnp.sum(rv), -jnp.sum(u * ru + v * rv))
    # adjugate of the symmetric normal matrix [[sw, 0, -su], [0, sw, -sv], [-su, -sv, suv]]
    a00, a11, a22 = sw * suv - sv * sv, sw * suv - su * su, sw * sw
    a01, a02, a12 = su * sv, su * sw, sv * sw
    det = sw * a00 - su * a02
    return (
        (a00 * b[0] + a01 * b[1] + a02 * b[2]) / det,
        (a01 * b[0] + a11 * b[1] + a12 * b[2]) / det,
        (a02 * b[0] + a12 * b[1] + a22 * b[2]) / det,
    )


def _homography(xy: Array, m: Array, w: Array) -> Array:
    """DLT homography H (3x3) with [m, 1] ~ H [xy, 1], Hartley-normalised, weighted rows (in
    closed form for four points, which it fits exactly)."""

    def similarity(p):
        wsum = jnp.maximum(jnp.sum(w), jnp.finfo(p.dtype).tiny)
        mu = jnp.sum(w[:, None] * p, axis=0) / wsum
        spread = jnp.sum(w * jnp.linalg.norm(p - mu, axis=-1)) / wsum
        s = jnp.sqrt(2.0) / jnp.maximum(spread, jnp.finfo(p.dtype).tiny)
        one, zero = jnp.ones_like(s), jnp.zeros_like(s)
        T = jnp.stack(
            [
                jnp.stack([s, zero, -s * mu[0]]),
                jnp.stack([zero, s, -s * mu[1]]),
                jnp.stack([zero, zero, one]),
            ]
        )
        T_inv = jnp.stack(
            [
                jnp.stack([1 / s, zero, mu[0]]),
                jnp.stack([zero, 1 / s, mu[1]]),
                jnp.stack([zero, zero, one]),
            ]
        )
        return T, T_inv, (p - mu) * s

    T_src, _, a = similarity(xy)
    _, T_dst_inv, b = similarity(m)
    if xy.shape[0] == 4:
        # Four points determine H exactly: the DLT's null vector, in closed form.
        Hn = matmul(_square_to_quad(b), _adjugate3(_square_to_quad(a)))
    else:
        one, zero = jnp.ones_like(a[:, :1]), jnp.zeros_like(a[:, :1])
        row_u = jnp.concatenate([a, one, zero, zero, zero, -b[:, :1] * a, -b[:, :1]], axis=-1)
        row_v = jnp.concatenate([zero, zero, zero, a, one, -b[:, 1:] * a, -b[:, 1:]], axis=-1)
        sw = jnp.sqrt(w)[:, None]
        A = jnp.concatenate([row_u * sw, row_v * sw], axis=0)
        Hn = _null_vector(A).reshape(3, 3)
    H = matmul(matmul(T_dst_inv, Hn), T_src)
    return H / jnp.where(H[2, 2] < 0, -1.0, 1.0)


def _adjugate3(M: Array) -> Array:
    """Adjugate of a 3x3 matrix (its inverse times its determinant)."""
    return jnp.stack([jnp.cross(M[1], M[2]), jnp.cross(M[2], M[0]), jnp.cross(M[0], M[1])], -1)


def _square_to_quad(p: Float[Array, "4 2"]) -> Float[Array, "3 3"]:
    """A homography (up to scale) taking the unit square's corners (0, 0), (1, 0), (1, 1),
    (0, 1) to the quadrilateral `p` (Heckbert 1989, multiplied through by its denominator so
    that nothing is divided)."""
    x, y = p[:, 0], p[:, 1]
    sx, sy = x[0] - x[1] + x[2] - x[3], y[0] - y[1] + y[2] - y[3]
    dx1, dx2, dy1, dy2 = x[1] - x[2], x[3] - x[2], y[1] - y[2], y[3] - y[2]
    den = dx1 * dy2 - dx2 * dy1
    g, h = sx * dy2 - dx2 * sy, dx1 * sy - sx * dy1
    return jnp.stack(
        [
            jnp.stack([den * (x[1] - x[0]) + g * x[1], den * (x[3] - x[0]) + h * x[3], den * x[0]]),
            jnp.stack([den * (y[1] - y[0]) + g * y[1], den * (y[3] - y[0]) + h * y[3], den * y[0]]),
            jnp.stack([g, h, den]),
        ]
    )


def _ippe_rotations(H: Array) -> tuple[tuple, tuple]:
    """The two IPPE rotations camera_R_plane (rows of scalars) from a plane->normalised-image
    homography whose plane origin is the point of expansion (the plane points' centroid).
    Written on scalars: vmapped, every product of the small matrices below is elementwise."""
    h = [[H[i, j] for j in range(3)] for i in range(3)]
    p, q = h[0][2] / h[2][2], h[1][2] / h[2][2]
    # Jacobian of the homography at the plane origin.
    J = [[(h[i][j] - c * h[2][j]) / h[2][2] for j in range(2)] for i, c in enumerate((p, q))]
    # Rotation Rv taking the optical axis onto the line of sight through (p, q): with
    # u = e_z x v and c = v . e_z, Rv = I + [u]x + [u]x^2 / (1 + c) (c > 0: no singularity).
    norm = jnp.sqrt(p * p + q * q + 1.0)
    v0, v1, v2 = p / norm, q / norm, 1.0 / norm
    k = 1.0 / (1.0 + v2)
    Rv = (
        (1.0 - v0 * v0 * k, -v0 * v1 * k, v0),
        (-v0 * v1 * k, 1.0 - v1 * v1 * k, v1),
        (-v0, -v1, 1.0 - (v0 * v0 + v1 * v1) * k),
    )
    # [I2 | -(p, q)] Rv = [B | 0], so J = B R'[:2, :2] / depth with R = Rv R'.
    B = [[Rv[i][j] - c * Rv[2][j] for j in range(2)] for i, c in enumerate((p, q))]
    det = B[0][0] * B[1][1] - B[0][1] * B[1][0]
    B_inv = ((B[1][1] / det, -B[0][1] / det), (-B[1][0] / det, B[0][0] / det))
    A = [[B_inv[i][0] * J[0][j] + B_inv[i][1] * J[1][j] for j in range(2)] for i in range(2)]
    # The 2x2 top-left block of a rotation has largest singular value 1: gamma = 1 / depth.
    ata00 = A[0][0] * A[0][0] + A[1][0] * A[1][0]
    ata01 = A[0][0] * A[0][1] + A[1][0] * A[1][1]
    ata11 = A[0][1] * A[0][1] + A[1][1] * A[1][1]
    gamma = jnp.sqrt(0.5 * (ata00 + ata11 + jnp.sqrt((ata00 - ata11) ** 2 + 4 * ata01**2)))
    Rt = [[a / gamma for a in row] for row in A]
    b0 = jnp.sqrt(jnp.maximum(1.0 - Rt[0][0] ** 2 - Rt[1][0] ** 2, 0.0))
    b1 = jnp.sqrt(jnp.maximum(1.0 - Rt[0][1] ** 2 - Rt[1][1] ** 2, 0.0))
    # Orthogonal first two columns: Rt00 Rt01 + Rt10 Rt11 + b0 b1 = 0 fixes sign(b1) given b0.
    b1 = jnp.where(Rt[0][0] * Rt[0][1] + Rt[1][0] * Rt[1][1] > 0, -b1, b1)

    def complete(s):
        c1 = (Rt[0][0], Rt[1][0], s * b0)
        c2 = (Rt[0][1], Rt[1][1], s * b1)
        c3 = _cross(c1, c2)
        return tuple(
            tuple(sum(Rv[i][k] * c[k] for k in range(3)) for c in (c1, c2, c3)) for i in range(3)
        )

    return complete(1.0), complete(-1.0)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _plane_frame(centroid: Array, evecs: Array) -> tuple[Array, Array]:
    """plane_T_object `(R, t)` from the object points' PCA: origin at the weighted centroid, z
    along the smallest principal axis."""
    normal, e1 = evecs[:, 0], evecs[:, 2]
    e2 = jnp.cross(normal, e1)
    R = jnp.stack([e1, e2, normal], axis=0)  # rows: plane axes in object coordinates
    return R, -jnp.sum(R * centroid, axis=-1)


def ippe_candidates(
    X: Float[Array, "N 3"], m: Float[Array, "N 2"], w: Float[Array, " N"], object_pca
) -> SE3:
    """The two IPPE poses camera_T_object, stacked as an SE3 of batch `(2,)`, for object points
    `X` on (or near: their best-fit plane is used) a plane; `object_pca` from `weighted_pca`."""
    centroid, _, evecs = object_pca
    R_plane, t_plane = _plane_frame(centroid, evecs)  # plane_T_object
    P = matmul(X, R_plane.T) + t_plane
    H = _homography(P[:, :2], m, w)
    flat = P.at[:, 2].set(0.0)

    # The rotation as the product of quaternions camera_R_plane plane_R_object, so that its
    # sign is that of the composition of the two poses.
    plane_q = SO3.from_matrix(R_plane)

    def pose(R):
        t = _translation_given_rotation(R, flat, m, w)
        t_object = [sum(R[i][k] * t_plane[k] for k in range(3)) + t[i] for i in range(3)]
        rotation = SO3.from_matrix(jnp.stack([jnp.stack(row) for row in R])) @ plane_q
        return SE3.from_rotation_and_translation(rotation, jnp.stack(t_object))

    first, second = _ippe_rotations(H)
    return jax.tree.map(lambda a, b: jnp.stack([a, b]), pose(first), pose(second))


def _epnp(X: Array, m: Array, w: Array, object_pca) -> SE3:
    """EPnP's three starts camera_T_object (an SE3 of batch (3,)) for n >= 4 non-coplanar
    points, from normalised image coordinates m."""
    dtype = X.dtype
    centroid, evals, evecs = object_pca
    scale = jnp.sqrt(jnp.maximum(evals, evals[-1] * jnp.finfo(dtype).eps))
    # Control points: the centroid and one point along each principal axis.
    ctrl_w = jnp.concatenate([centroid[None], centroid + (evecs * scale).T], axis=0)  # (4, 3)
    a123 = (X - centroid) @ evecs / scale
    alphas = jnp.concatenate([1.0 - jnp.sum(a123, axis=-1, keepdims=True), a123], axis=-1)
    one, zero = jnp.ones_like(m[:, 0]), jnp.zeros_like(m[:, 0])
    coef_u = jnp.stack([one, zero, -m[:, 0]], axis=-1)  # (N, 3)
    coef_v = jnp.stack([zero, one, -m[:, 1]], axis=-1)
    rows_u = (alphas[:, :, None] * coef_u[:, None, :]).reshape(-1, 12)
    rows_v = (alphas[:, :, None] * coef_v[:, None, :]).reshape(-1, 12)
    sw = jnp.sqrt(w)[:, None]
    M = jnp.concatenate([rows_u * sw, rows_v * sw], axis=0)
    kernel = _epnp_kernel(M, jnp.sum(w > 0)).reshape(4, 4, 3)  # (k, control, xyz)

    pairs_a = jnp.array([0, 0, 0, 1, 1, 2])
    pairs_b = jnp.array([1, 2, 3, 2, 3, 3])
    dist_w = jnp.sum((ctrl_w[pairs_a] - ctrl_w[pairs_b]) ** 2, axis=-1)  # (6,)
    dk = kernel[:, pairs_a] - kernel[:, pairs_b]  # (4, 6, 3)

    def dist_c(beta):
        d = jnp.einsum("k,kpi->pi", beta, dk)
        return jnp.sum(d * d, axis=-1)

    # Linear estimates of beta from subsets of the products beta_k beta_l (EPnP's N = 4, 2, 3
    # approximations), then Gauss-Newton on all four betas.
    gram = jnp.einsum("kpi,lpi->pkl", dk, dk)  # (6, 4, 4): <dk_k, dk_l> per pair

    approximations = (
        [(0, 0), (0, 1), (0, 2), (0, 3)],
        [(0, 0), (0, 1), (1, 1)],
        [(0, 0), (0, 1), (1, 1), (0, 2), (1, 2)],
    )
    # One batched least-squares solve for all three (zero columns pad them to five unknowns;
    # the minimum-norm solution gives those zero).
    systems = jnp.stack(
        [
            jnp.stack(
                [gram[:, i, j] * (1.0 if i == j else 2.0) for i, j in products]
                + [jnp.zeros_like(dist_w)] * (5 - len(products)),
                axis=-1,
            )
            for products in approximations
        ]
    )
    solutions = jax.vmap(lambda A: jnp.linalg.lstsq(A, dist_w)[0])(systems)

    def linear_init(products, sol):
        value = dict(zip(products, sol[: len(products)], strict=True))
        b11 = value[(0, 0)]
        sign = jnp.where(b11 < 0, -1.0, 1.0)
        b1 = jnp.sqrt(jnp.abs(b11))
        safe_b1 = jnp.where(b1 > 0, b1, 1.0)
        beta = jnp.zeros(4, dtype).at[0].set(b1)
        if (1, 1) in value:
            b2 = jnp.sqrt(jnp.abs(value[(1, 1)]))
            beta = beta.at[1].set(jnp.where(sign * value[(0, 1)] < 0, -b2, b2))
        for k in (1, 2, 3):
            if (0, k) in value and (k, k) not in value:
                beta = beta.at[k].set(sign * value[(0, k)] / safe_b1)
        return beta

    inits = jnp.stack(
        [linear_init(p, sol) for p, sol in zip(approximations, solutions, strict=True)]
    )

    def gauss_newton(beta):
        def step(_, b):
            r = dist_c(b) - dist_w
            Jb = jax.jacfwd(dist_c)(b)
            JtJ = Jb.T @ Jb
            damping = 1e-9 * jnp.trace(JtJ) + jnp.finfo(dtype).tiny
            return b - jnp.linalg.solve(JtJ + damping * jnp.eye(4, dtype=dtype), Jb.T @ r)

        return jax.lax.fori_loop(0, 5, step, beta)

    def camera_points(beta):
        Xc = alphas @ jnp.einsum("k,kci->ci", beta, kernel)
        return jnp.where(jnp.sum(w * Xc[:, 2]) < 0, -Xc, Xc)  # in front of the camera

    Xc = jax.vmap(lambda b: camera_points(gauss_newton(b)))(inits)  # (3, N, 3)
    # align's pose, not kabsch's: a problem without weight starts from the identity (the
    # solver's status reports it), never from NaN.
    return align(jnp.broadcast_to(X, Xc.shape), Xc, jnp.broadcast_to(w, Xc.shape[:-1])).pose


def general_starts(
    X: Float[Array, "N 3"], m: Float[Array, "N 2"], w: Float[Array, " N"], object_pca
) -> SE3:
    """Five starts camera_T_object (SE3 of batch `(5,)`) for any point set: EPnP's three, then
    the two IPPE poses on the best-fit plane (EPnP is ill-posed for coplanar points)."""
    epnp = _epnp(X, m, w, object_pca)
    ippe = ippe_candidates(X, m, w, object_pca)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), epnp, ippe)
