"""Compiled per-ray kernels of the renderer (numba, no GIL).

The renderer's physics is written out in :mod:`tofhil.sim.render`; these loops fuse the
per-ray arithmetic that numpy would spread over dozens of temporary arrays: hit refinement
and shadow-ray set-up (:func:`vertex`), and the emitter connection, phasor accumulation and
bounce sampling (:func:`connect_and_bounce`). Each loop touches every ray once.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tofhil.sim import embree4 as eda

_INV_PI = 1.0 / math.pi


@njit(nogil=True, cache=True, inline="always")
def _pow(c, n):  # pragma: no cover
    """c**n, by multiplication for small integer n (the usual cos^n beams; pow() is slow)."""
    if n == 0.0:
        return 1.0
    if n <= 16.0 and n == math.floor(n):
        p = c
        for _ in range(int(n) - 1):
            p *= c
        return p
    return c ** n


@njit(nogil=True, cache=True, inline="always")
def _beam(ce, cos_n, beam):  # pragma: no cover
    """The emitter's relative intensity at ``cos(theta) = ce``: ``cos^n`` on the forward
    hemisphere for ``cos_n >= 0``; else the table ``beam`` = [theta_deg, values] linearly
    interpolated in theta as ``BeamProfile.relative`` does (np.interp: the first value before
    the table, 0 after it); a one-column table is that value over the whole sphere (isotropic:
    no arccos)."""
    if cos_n >= 0.0:
        return _pow(ce, cos_n) if ce > 0.0 else 0.0
    nt = beam.shape[1]
    if nt == 1:
        return beam[1, 0]
    th = math.acos(min(max(ce, -1.0), 1.0)) * (180.0 / math.pi)
    if th < beam[0, 0]:
        return beam[1, 0]
    if th >= beam[0, nt - 1]:
        return beam[1, nt - 1] if th == beam[0, nt - 1] else 0.0
    j = np.searchsorted(beam[0], th, side="right") - 1
    slope = (beam[1, j + 1] - beam[1, j]) / (beam[0, j + 1] - beam[0, j])
    return slope * (th - beam[0, j]) + beam[1, j]


@njit(nogil=True, cache=True)
def vertex(idx, prim, tfar, bu, bv, org, shared, dirs, path_in, plane_c, normal, vnormal, smooth,
           emitter_pos, emitter_axis, eps, cos_n, i0,
           x, ngf, nf, wo, wi, r1, cos_s, cos_e, t_out, path, irr, so, sd, sdist):  # pragma: no cover
    """Surface vertex of each hit ray ``idx[j]``: float64 hit point on the triangle's plane,
    normals faced toward the incoming ray (two-sided surfaces), direction and distance to the
    emitter, its irradiance ``E = I cos(theta_s) / r^2`` for a cos^n beam (``I = i0 cos^n``;
    ``cos_n < 0``: left to the caller) and the float32 shadow ray (origin lifted by ``eps``
    along the normal)."""
    for j in range(idx.shape[0]):
        i = idx[j]
        p = prim[i]
        if shared:
            ox, oy, oz = org[0, 0], org[0, 1], org[0, 2]
        else:
            ox, oy, oz = org[i, 0], org[i, 1], org[i, 2]
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        nx, ny, nz = normal[p, 0], normal[p, 1], normal[p, 2]
        dn = dx * nx + dy * ny + dz * nz
        te = np.float64(tfar[i])
        t = te
        if dn != 0.0:
            tr = (plane_c[p] - (ox * nx + oy * ny + oz * nz)) / dn
            if abs(tr - te) < 1e-4 * max(1.0, te):
                t = tr
        px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
        x[j, 0], x[j, 1], x[j, 2] = px, py, pz
        wo[j, 0], wo[j, 1], wo[j, 2] = -dx, -dy, -dz
        s = 1.0 if dn < 0.0 else -1.0          # face the normal toward -d
        gx, gy, gz = s * nx, s * ny, s * nz
        ngf[j, 0], ngf[j, 1], ngf[j, 2] = gx, gy, gz
        sx, sy, sz = gx, gy, gz
        if smooth:
            sx, sy, sz = _shading_normal(vnormal, p, np.float64(bu[i]), np.float64(bv[i]), s, gx, gy, gz, dx, dy, dz)
        nf[j, 0], nf[j, 1], nf[j, 2] = sx, sy, sz
        ex, ey, ez = emitter_pos[0] - px, emitter_pos[1] - py, emitter_pos[2] - pz
        r = math.sqrt(ex * ex + ey * ey + ez * ez)
        ex, ey, ez = ex / r, ey / r, ez / r
        wi[j, 0], wi[j, 1], wi[j, 2] = ex, ey, ez
        r1[j] = r
        cs = sx * ex + sy * ey + sz * ez
        ce = -(ex * emitter_axis[0] + ey * emitter_axis[1] + ez * emitter_axis[2])
        cos_s[j] = cs
        cos_e[j] = ce
        if cos_n >= 0.0:
            irr[j] = i0 * _pow(ce, cos_n) * cs / (r * r) if (cs > 0.0 and ce > 0.0) else 0.0
        t_out[j] = t
        path[j] = path_in[i] + t
        so[j, 0], so[j, 1], so[j, 2] = px + eps * gx, py + eps * gy, pz + eps * gz
        sd[j, 0], sd[j, 1], sd[j, 2] = ex, ey, ez
        sdist[j] = r - 2.0 * eps


@njit(nogil=True, cache=True, inline="always")
def _brdf(rho, rs, ns, nx, ny, nz, ix, iy, iz, ox, oy, oz):  # pragma: no cover
    f = rho * _INV_PI
    if rs > 0.0:
        cn = nx * ix + ny * iy + nz * iz
        rx, ry, rz = 2.0 * cn * nx - ix, 2.0 * cn * ny - iy, 2.0 * cn * nz - iz
        ca = rx * ox + ry * oy + rz * oz
        if ca > 0.0:
            f += rs * (ns + 2.0) / (2.0 * math.pi) * min(ca, 1.0) ** ns
    return f


@njit(nogil=True, cache=True, inline="always")
def _shading_normal(vnormal, p, a, b, sg, gx, gy, gz, dx, dy, dz):  # pragma: no cover
    """The vertex normals of triangle ``p`` interpolated at barycentrics ``(a, b)``, turned
    to face the ray like the geometric normal (sign ``sg``); the geometric normal ``g`` where
    the interpolated one faces away from the ray (a silhouette)."""
    c = 1.0 - a - b
    sx = c * vnormal[p, 0, 0] + a * vnormal[p, 1, 0] + b * vnormal[p, 2, 0]
    sy = c * vnormal[p, 0, 1] + a * vnormal[p, 1, 1] + b * vnormal[p, 2, 1]
    sz = c * vnormal[p, 0, 2] + a * vnormal[p, 1, 2] + b * vnormal[p, 2, 2]
    ln = math.sqrt(sx * sx + sy * sy + sz * sz)
    sx, sy, sz = sg * sx / ln, sg * sy / ln, sg * sz / ln
    if -(sx * dx + sy * dy + sz * dz) < 0.0:
        return gx, gy, gz
    return sx, sy, sz


@njit(nogil=True, cache=True, inline="always")
def _cosine_direction(a1, a2, nx, ny, nz):  # pragma: no cover
    """A cosine-weighted direction about the unit normal ``n`` from two uniform numbers, in the
    orthonormal frame of Duff et al. 2017 (no branch on the normal's direction but its sign)."""
    rr = math.sqrt(a1)
    phi = 2.0 * math.pi * a2
    lx, ly, lz = rr * math.cos(phi), rr * math.sin(phi), math.sqrt(max(0.0, 1.0 - a1))
    sg = 1.0 if nz >= 0.0 else -1.0
    aa = -1.0 / (sg + nz)
    bb = nx * ny * aa
    t1x, t1y, t1z = 1.0 + sg * nx * nx * aa, sg * bb, -sg * nx
    t2x, t2y, t2z = bb, sg + ny * ny * aa, -ny
    return (lx * t1x + ly * t2x + lz * nx, lx * t1y + ly * t2y + lz * ny, lx * t1z + ly * t2z + lz * nz)


@njit(nogil=True, cache=True, inline="always")
def _sincos(x):  # pragma: no cover
    """(sin x, cos x) with one shared argument reduction: x - n pi/2 in three parts (Cody and
    Waite, fdlibm's constants: exact to well below an ulp for |x| < 2^20 pi/2, far beyond
    any optical path's phase here) and fdlibm's minimax polynomials on [-pi/4, pi/4]
    (< 1 ulp). One of these costs about what one libm sin or cos call does."""
    n = math.floor(x * 0.63661977236758134308 + 0.5)
    r = ((x - n * 1.57079632673412561417e+00) - n * 6.07710050630396597660e-11) - n * 2.02226624871116645580e-21
    z = r * r
    s = r + r * z * (-1.66666666666666324348e-01 + z * (8.33333333332248946124e-03 + z * (
        -1.98412698298579493134e-04 + z * (2.75573137070700676789e-06 + z * (
            -2.50507602534068634195e-08 + z * 1.58969099521155010221e-10)))))
    hz = 0.5 * z
    w = 1.0 - hz
    c = w + (((1.0 - w) - hz) + z * z * (4.16666666666666019037e-02 + z * (-1.38888888888741095749e-03 + z * (
        2.48015872894767294178e-05 + z * (-2.75573143513906633035e-07 + z * (
            2.08757232129817482790e-09 - z * 1.13596475577881948265e-11))))))
    # Quadrant by selects, not branches (the phase of a random path is random: a branch on it
    # is mispredicted half the time).
    q = int(n)
    swap = (q & 1) == 1
    sign_s = 1.0 - 2.0 * ((q >> 1) & 1)
    sign_c = 1.0 - 2.0 * (((q + 1) >> 1) & 1)
    return sign_s * (c if swap else s), sign_c * (s if swap else c)


@njit(nogil=True, cache=True, inline="always")
def _accumulate(acc_re, acc_im, power, trans, edges, k, nk, nbins, which, q, w, length):  # pragma: no cover
    """Add one light path of weight ``w`` and optical length ``length`` to pixel ``q``: its
    power, its phasor ``w exp(i k L)`` per frequency/harmonic (row ``which``: 0 direct, 1
    indirect) and, with a transient histogram, its length bin."""
    power[q] += w
    for m in range(nk):
        sn, cs = _sincos(k[m] * length)
        acc_re[which, m, q] += w * cs
        acc_im[which, m, q] += w * sn
    if nbins > 0:
        b = np.searchsorted(edges, length, side="right") - 1
        if b >= 0 and b < nbins:
            trans[q, b] += w


@njit(nogil=True, cache=True)
def connect_and_bounce(irr, blocked, rho, rs, ns, nf, ngf, wo, wi, r1, x, beta, path, local, which,
                       k, acc_re, acc_im, power, edges, trans, do_bounce, u1, u2, eps,
                       nb_org, nb_dir, nb_keep):  # pragma: no cover
    """Add each vertex's emitter connection ``w = beta f_r E`` with path length ``path + r1``
    to its pixel's phasors (and transient bins), then draw the next direction cosine-weighted
    about the shading normal (throughput ``f_r pi``). Returns the number of continued paths;
    their rows go to ``nb_keep`` and their rays to ``nb_org``/``nb_dir``; ``beta`` is updated
    in place."""
    nk = k.shape[0]
    nbins = edges.shape[0] - 1
    count = 0
    for j in range(irr.shape[0]):
        nx, ny, nz = nf[j, 0], nf[j, 1], nf[j, 2]
        ox, oy, oz = wo[j, 0], wo[j, 1], wo[j, 2]
        e = irr[j]
        if e > 0.0 and not blocked[j]:
            w = beta[j] * e * _brdf(rho[j], rs[j], ns[j], nx, ny, nz, wi[j, 0], wi[j, 1], wi[j, 2], ox, oy, oz)
            if w > 0.0:
                _accumulate(acc_re, acc_im, power, trans, edges, k, nk, nbins, which, local[j], w, path[j] + r1[j])
        if not do_bounce:
            continue
        # Cosine-weighted direction in the frame of the shading normal (Duff et al. 2017).
        dx, dy, dz = _cosine_direction(u1[j], u2[j], nx, ny, nz)
        gx, gy, gz = ngf[j, 0], ngf[j, 1], ngf[j, 2]
        if dx * gx + dy * gy + dz * gz <= 0.0:    # below the geometric surface
            continue
        nbeta = beta[j] * math.pi * _brdf(rho[j], rs[j], ns[j], nx, ny, nz, dx, dy, dz, ox, oy, oz)
        beta[j] = nbeta
        if nbeta <= 0.0:
            continue
        nb_org[count, 0] = x[j, 0] + eps * gx
        nb_org[count, 1] = x[j, 1] + eps * gy
        nb_org[count, 2] = x[j, 2] + eps * gz
        nb_dir[count, 0], nb_dir[count, 1], nb_dir[count, 2] = dx, dy, dz
        nb_keep[count] = j
        count += 1
    return count


@njit(nogil=True, cache=True)
def trace_paths(scene, buf, org, shared, dirs, path0, beta0, local, U, bounces, normal, plane_c, vnormal,
                smooth, tri_object, rho_d, rho_s, n_s, emitter_pos, emitter_axis, eps, cos_n, i0, beam,
                k, acc_re, acc_im, power, ambient_unit, edges, trans, first_t, first_obj):  # pragma: no cover
    """Every sample's whole path in one loop, Embree called per ray (:mod:`tofhil.sim.embree4`).

    The same physics, in the same float32 rays, as :func:`vertex` and
    :func:`connect_and_bounce` applied bounce by bounce: sample ``s`` starts at ``org`` (one
    shared row or one per sample) along ``dirs[s]`` with path length ``path0[s]`` and
    throughput ``beta0[s]``, and draws bounce ``b``'s direction from ``U[s, 4 + 2b]`` and
    ``U[s, 5 + 2b]``. Uniform reflectance per object (no textures).
    The beam: ``cos^n`` for ``cos_n >= 0``, else the table ``beam`` (:func:`_beam`).
    ``first_t``/``first_obj`` get the primary hit (inf / -1 for a miss); ``ambient_unit`` the
    first vertex's albedo * beta / pi. Returns the number of rays traced.
    """
    addr, o = eda.record(buf)
    f = buf
    u = buf.view(np.uint32)
    nk = k.shape[0]
    nbins = edges.shape[0] - 1
    rays = 0
    for s in range(dirs.shape[0]):
        if shared:
            ox, oy, oz = org[0, 0], org[0, 1], org[0, 2]
        else:
            ox, oy, oz = org[s, 0], org[s, 1], org[s, 2]
        dx, dy, dz = dirs[s, 0], dirs[s, 1], dirs[s, 2]
        path_in = path0[s]
        beta = beta0[s]
        q = local[s]
        for bounce in range(bounces + 1):
            eda.set_ray(f, u, o, np.float32(ox), np.float32(oy), np.float32(oz),
                        np.float32(dx), np.float32(dy), np.float32(dz), np.float32(1e37))
            eda.rtc_intersect1(scene, addr, 0)
            rays += 1
            p = u[o + 17]
            if p == eda.INVALID_ID:
                if bounce == 0:
                    first_t[s] = np.inf
                    first_obj[s] = -1
                break
            nx, ny, nz = normal[p, 0], normal[p, 1], normal[p, 2]
            dn = dx * nx + dy * ny + dz * nz
            te = np.float64(f[o + 8])
            t = te
            if dn != 0.0:
                tr = (plane_c[p] - (ox * nx + oy * ny + oz * nz)) / dn
                if abs(tr - te) < 1e-4 * max(1.0, te):
                    t = tr
            px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
            sg = 1.0 if dn < 0.0 else -1.0
            gx, gy, gz = sg * nx, sg * ny, sg * nz
            sx, sy, sz = gx, gy, gz
            if smooth:
                sx, sy, sz = _shading_normal(vnormal, p, np.float64(f[o + 15]), np.float64(f[o + 16]), sg, gx, gy, gz,
                                             dx, dy, dz)
            ob = tri_object[p]
            rho, rs, ns = rho_d[ob], rho_s[ob], n_s[ob]
            path = path_in + t
            if bounce == 0:
                first_t[s] = t
                first_obj[s] = ob
                ambient_unit[q] += beta * (rho + rs) * _INV_PI
            ex, ey, ez = emitter_pos[0] - px, emitter_pos[1] - py, emitter_pos[2] - pz
            r = math.sqrt(ex * ex + ey * ey + ez * ez)
            ex, ey, ez = ex / r, ey / r, ez / r
            cs = sx * ex + sy * ey + sz * ez
            ce = -(ex * emitter_axis[0] + ey * emitter_axis[1] + ez * emitter_axis[2])
            irr = i0 * _beam(ce, cos_n, beam) * cs / (r * r) if cs > 0.0 else 0.0
            if irr > 0.0:
                eda.set_ray(f, u, o, np.float32(px + eps * gx), np.float32(py + eps * gy), np.float32(pz + eps * gz),
                            np.float32(ex), np.float32(ey), np.float32(ez), np.float32(r - 2.0 * eps))
                eda.rtc_occluded1(scene, addr, 0)
                rays += 1
                if not f[o + 8] < 0.0:        # tfar = -inf: blocked
                    w = beta * irr * _brdf(rho, rs, ns, sx, sy, sz, ex, ey, ez, -dx, -dy, -dz)
                    if w > 0.0:
                        _accumulate(acc_re, acc_im, power, trans, edges, k, nk, nbins, 0 if bounce == 0 else 1, q, w,
                                    path + r)
            if bounce == bounces:
                break
            ndx, ndy, ndz = _cosine_direction(U[s, 4 + 2 * bounce], U[s, 5 + 2 * bounce], sx, sy, sz)
            if ndx * gx + ndy * gy + ndz * gz <= 0.0:    # below the geometric surface
                break
            beta = beta * math.pi * _brdf(rho, rs, ns, sx, sy, sz, ndx, ndy, ndz, -dx, -dy, -dz)
            if beta <= 0.0:
                break
            ox, oy, oz = px + eps * gx, py + eps * gy, pz + eps * gz
            dx, dy, dz = ndx, ndy, ndz
            path_in = path
    return rays


@njit(nogil=True, cache=True)
def rotate_rows(v, R, out):  # pragma: no cover
    """``out = v @ R.T`` for [N, 3] rows, in the numpy expression's order
    ``(v0 R[k, 0] + v1 R[k, 1]) + v2 R[k, 2]`` (no fused multiply-add: bit-identical to it),
    without its five [N, 3] temporaries."""
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    for i in range(v.shape[0]):
        a, b, c = v[i, 0], v[i, 1], v[i, 2]
        out[i, 0] = a * r00 + b * r01 + c * r02
        out[i, 1] = a * r10 + b * r11 + c * r12
        out[i, 2] = a * r20 + b * r21 + c * r22
