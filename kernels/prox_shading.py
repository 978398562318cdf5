"""Eq. 2-3 shading of the proximity renderers (the reference's Phong-style model, Sec. 2.2.4).

    R.V = 2 (N.V)(N.L) - (V.L)                                       (Eq. 2)
    I   = I_a k_a + I_l (k_l max(N.L, 0) + k_s max(R.V, 0)^n)        (Eq. 3, clamped)

with N the unit surface normal, L the unit vector towards the (distant) light, V the unit vector
from the surface point to the camera.  Clamping choices (the paper's Eq. 3 has none):

* diffuse ``max(N.L, 0)``: a surface facing away from the light gets ambient light only;
* the specular term is added only when ``N.L > 0`` (no highlight on a self-shadowed surface) and
  uses ``max(R.V, 0)^n``;
* a zero normal (cuboid edge points) gets ambient light only, ``I = I_a k_a`` -- Eq. 2 with N = 0
  would otherwise give R.V = -(V.L), a spurious specular term.

Used by both renderers (:mod:`dualsight.kernels.prox_splat`, :mod:`dualsight.kernels.prox_raster`).
"""

import taichi as ti


@ti.func
def shade(p, n, L, ka, kl, ks, ne, Ia, Il):
    """Eq. 3 intensity (Eq. 2 for R.V) of one surface point, float32.

    p : 3-vector, the point in the camera frame (m; the camera is at the origin, so V = -p / |p|).
    n : 3-vector surface normal in the camera frame, any length (0 = an edge point: ambient only).
    L : unit 3-vector towards the light, camera frame.
    ka, kl, ks, ne : the material's ambient, diffuse and specular coefficients and specular exponent.
    Ia, Il : ambient and light intensities (image units).
    """
    V = -p / p.norm()
    I = Ia * ka
    nn = n.norm_sqr()
    if nn > 0:
        N = n / ti.sqrt(nn)
        NL = N.dot(L)
        if NL > 0:
            RV = 2.0 * N.dot(V) * NL - V.dot(L)          # Eq. 2
            spec = 0.0
            if RV > 0:
                spec = ks * ti.pow(RV, ne)
            I += Il * (kl * NL + spec)
    return I
