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

from tofhil import camera_kernels as _camera_kernels, lens_models as _lens_models
from tofhil.camera_kernels import pixel_ray
from tofhil.numba_cache import drop_stale_cache as _drop_stale_cache
from tofhil.sim import dielectric as _dielectric
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


@njit(nogil=True, cache=True, inline="always")
def _plane_t(nx, ny, nz, pc, ox, oy, oz, dx, dy, dz, te):  # pragma: no cover
    """Embree's float32 hit distance ``te`` refined in float64 on the plane ``n . x = pc``
    (kept when the two agree to 1e-4, i.e. not at a grazing angle), and ``d . n``. Scalars
    only: an array passed to a helper costs the hot loops an atomic reference count each."""
    dn = dx * nx + dy * ny + dz * nz
    t = te
    if dn != 0.0:
        tr = (pc - (ox * nx + oy * ny + oz * nz)) / dn
        if abs(tr - te) < 1e-4 * max(1.0, te):
            t = tr
    return t, dn


@njit(nogil=True, cache=True, inline="always")
def _plane_hit(normal, plane_c, p, ox, oy, oz, dx, dy, dz, te):  # pragma: no cover
    """:func:`_plane_t` on the plane of triangle ``p``."""
    return _plane_t(normal[p, 0], normal[p, 1], normal[p, 2], plane_c[p], ox, oy, oz, dx, dy, dz, te)


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
        t, dn = _plane_hit(normal, plane_c, p, ox, oy, oz, dx, dy, dz, np.float64(tfar[i]))
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
    """A cosine-weighted direction about the unit normal ``n`` from two uniform numbers: the
    unit square mapped onto the disk by Shirley and Chiu's concentric map (area-preserving,
    so uniform on the disk; it keeps the square's strata compact, where the polar map
    ``sqrt(a1), 2 pi a2`` stretches them into thin wedges), lifted to the hemisphere
    (Malley), in the orthonormal frame of Duff et al. 2017 (no branch on the normal's
    direction but its sign)."""
    a = 2.0 * a1 - 1.0
    b = 2.0 * a2 - 1.0
    # Selects, not branches (which half of the square is random: a branch on it is
    # mispredicted half the time); one division either way (a = b = 0: the pole).
    use_a = a * a > b * b
    rr = a if use_a else b
    num = b if use_a else a
    den = rr if rr != 0.0 else 1.0
    q = (0.25 * math.pi) * (num / den)
    phi = q if use_a else 0.5 * math.pi - q
    sn, cs = _sincos(phi)           # one shared range reduction (libm's cos and sin: two)
    lx, ly, lz = rr * cs, rr * sn, math.sqrt(max(0.0, 1.0 - rr * rr))
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
    indirect; or :func:`share_row`) and, with a transient histogram, its length bin."""
    power[q] += w
    for m in range(nk):
        sn, cs = _sincos(k[m] * length)
        acc_re[which, m, q] += w * cs
        acc_im[which, m, q] += w * sn
    if nbins > 0:
        b = np.searchsorted(edges, length, side="right") - 1
        if b >= 0 and b < nbins:
            trans[q, b] += w


@njit(nogil=True, cache=True, inline="always")
def share_row(bounce, src, n_obj):  # pragma: no cover
    """The accumulator row of a path: 0 direct / 1 indirect, or with ``n_obj > 0`` (multipath
    shares) ``bounce * n_obj + src``, ``src`` the object the light came from (see render)."""
    if n_obj == 0:
        return 0 if bounce == 0 else 1
    return bounce * n_obj + src


@njit(nogil=True, cache=True)
def connect_and_bounce(irr, blocked, rho, rs, ns, nf, ngf, wo, wi, r1, x, beta, path, local, which,
                       k, acc_re, acc_im, power, edges, trans, do_bounce, u1, u2, eps,
                       nb_org, nb_dir, nb_keep):  # pragma: no cover
    """Add each vertex's emitter connection ``w = beta f_r E`` with path length ``path + r1``
    to its pixel's phasors (row ``which[j]``) and transient bins, then draw the next direction cosine-weighted
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
                _accumulate(acc_re, acc_im, power, trans, edges, k, nk, nbins, which[j], local[j], w, path[j] + r1[j])
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
                k, acc_re, acc_im, power, ambient_unit, edges, trans, first_t, first_obj, n_obj=0,
                share=1):  # pragma: no cover
    """Every sample's whole path in one loop, Embree called per packet of ``eda.LANES``
    samples (:mod:`tofhil.sim.embree4`; ``buf`` from :func:`eda.packet_buffer`).

    The same physics, in the same float32 rays, as :func:`vertex` and
    :func:`connect_and_bounce` applied bounce by bounce: sample ``s`` starts at ``org`` (one
    shared row or one per sample) along ``dirs[s]`` with path length ``path0[s]`` and
    throughput ``beta0[s]``, and draws bounce ``b``'s direction from ``U[s, 4 + 2b]`` and
    ``U[s, 5 + 2b]``. Uniform reflectance per object (no textures).
    The beam: ``cos^n`` for ``cos_n >= 0``, else the table ``beam`` (:func:`_beam`).
    ``first_t``/``first_obj`` get the primary hit (inf / -1 for a miss); ``ambient_unit`` the
    first vertex's albedo * beta / pi. ``n_obj > 0``: rows by bounce and source object
    (:func:`share_row`). ``share > 1`` (a divisor of ``eda.LANES``): each group of ``share``
    consecutive samples continues the camera ray of its first (:func:`render.camera_ray_share`):
    that ray and its emitter connection are traced once, the connection added ``share`` times
    over, and every sample of the group bounces on with its own uniforms. Returns the number
    of rays traced.

    Consecutive samples go bounce by bounce as one packet: one ``rtcIntersect8`` for their
    rays and one ``rtcOccluded8`` for their shadow rays, so the per-call cost of Embree and the
    spilling around a foreign call are paid once per packet, and the shading loops between the
    calls stay free of calls. Each sample's arithmetic is the per-ray loop's; only the order
    in which a pixel's samples are added changes (float rounding).
    """
    # No array goes to a helper inside the loops (the stores of a ray, the plane refinement,
    # the accumulation are written out): numba would count a reference per call, an atomic
    # operation on a cache line the other render thread shares (15 % of the time).
    L = eda.LANES
    INV = eda.INVALID_ID
    o, addr = eda.packet_record(buf)
    f = buf
    u = buf.view(np.uint32)
    so = o + 256                     # shadow-ray packet
    vo, svo = o + 384, o + 400       # valid masks (int32: -1 on, 0 off)
    s_addr, v_addr, sv_addr = addr + 4 * 256, addr + 4 * 384, addr + 4 * 400
    nk = k.shape[0]
    nbins = edges.shape[0] - 1
    rays = 0
    n = dirs.shape[0]
    # Lane state: ray, path length so far, throughput, pixel, source object, sample, alive.
    lo = np.empty((L, 3))
    ld = np.empty((L, 3))
    lpath = np.empty(L)
    lbeta = np.empty(L)
    lq = np.empty(L, np.int64)
    lsrc = np.zeros(L, np.int64)
    ls = np.empty(L, np.int64)
    alive = np.zeros(L, np.bool_)
    # Per-lane vertex results kept from the shading loop for the connection and the bounce.
    lw = np.empty(L)                 # beta * E (the connection's weight without f_r)
    lx = np.empty((L, 3))
    lg = np.empty((L, 3))
    lsn = np.empty((L, 3))
    le = np.empty((L, 3))
    lr = np.empty(L)
    lpv = np.empty(L)
    lmat = np.empty((L, 3))
    # The beam: cos^n, one value over the whole sphere, or the table (:func:`_beam`).
    beam_flat = cos_n < 0.0 and beam.shape[1] == 1
    beam_c = beam[1, 0] if beam_flat else 0.0
    for s0 in range(0, n, L):
        m = min(L, n - s0)
        for j in range(L):
            alive[j] = j < m
            if j < m:
                s = s0 + j
                if shared:
                    lo[j, 0], lo[j, 1], lo[j, 2] = org[0, 0], org[0, 1], org[0, 2]
                else:
                    lo[j, 0], lo[j, 1], lo[j, 2] = org[s, 0], org[s, 1], org[s, 2]
                ld[j, 0], ld[j, 1], ld[j, 2] = dirs[s, 0], dirs[s, 1], dirs[s, 2]
                lpath[j] = path0[s]
                lbeta[j] = beta0[s]
                lq[j] = local[s]
                lsrc[j] = 0
                ls[j] = s
        for bounce in range(bounces + 1):
            live = 0
            for j in range(L):
                if alive[j] and (bounce > 0 or j % share == 0):
                    # ray j of the packet: set_ray's fields, each LANES words apart
                    f[o + j] = np.float32(lo[j, 0])
                    f[o + L + j] = np.float32(lo[j, 1])
                    f[o + 2 * L + j] = np.float32(lo[j, 2])
                    f[o + 3 * L + j] = 0.0
                    f[o + 4 * L + j] = np.float32(ld[j, 0])
                    f[o + 5 * L + j] = np.float32(ld[j, 1])
                    f[o + 6 * L + j] = np.float32(ld[j, 2])
                    f[o + 7 * L + j] = 0.0
                    f[o + 8 * L + j] = np.float32(1e37)
                    u[o + 9 * L + j] = INV
                    u[o + 10 * L + j] = 0
                    u[o + 11 * L + j] = 0
                    u[o + 17 * L + j] = INV
                    u[o + 18 * L + j] = INV
                    u[o + 19 * L + j] = INV
                    u[vo + j] = INV
                    live += 1
                else:
                    u[vo + j] = 0
            if live == 0:
                break
            eda.rtc_intersect8(v_addr, scene, addr, 0)
            rays += live
            shadows = 0
            for j in range(L):
                u[svo + j] = 0
                if not alive[j]:
                    continue
                if bounce == 0 and j % share != 0:
                    # a follower: the group's camera ray and first vertex (lane j - j % share,
                    # done in this loop already); its emitter connection is the leader's
                    lead = j - j % share
                    if not alive[lead]:
                        first_t[ls[j]] = np.inf
                        first_obj[ls[j]] = -1
                        alive[j] = False
                        continue
                    lo[j, 0], lo[j, 1], lo[j, 2] = lo[lead, 0], lo[lead, 1], lo[lead, 2]
                    ld[j, 0], ld[j, 1], ld[j, 2] = ld[lead, 0], ld[lead, 1], ld[lead, 2]
                    lbeta[j] = lbeta[lead]
                    lsrc[j] = lsrc[lead]
                    first_t[ls[j]] = first_t[ls[lead]]
                    first_obj[ls[j]] = first_obj[ls[lead]]
                    lw[j], lr[j], lpv[j] = lw[lead], lr[lead], lpv[lead]
                    for c in range(3):
                        lx[j, c], lg[j, c], lsn[j, c] = lx[lead, c], lg[lead, c], lsn[lead, c]
                        le[j, c], lmat[j, c] = le[lead, c], lmat[lead, c]
                    ambient_unit[lq[j]] += lbeta[j] * (lmat[j, 0] + lmat[j, 1]) * _INV_PI
                    continue
                p = u[o + 17 * L + j]
                if p == eda.INVALID_ID:
                    if bounce == 0:
                        first_t[ls[j]] = np.inf
                        first_obj[ls[j]] = -1
                    alive[j] = False
                    continue
                ox, oy, oz = lo[j, 0], lo[j, 1], lo[j, 2]
                dx, dy, dz = ld[j, 0], ld[j, 1], ld[j, 2]
                nx, ny, nz = normal[p, 0], normal[p, 1], normal[p, 2]
                t, dn = _plane_t(nx, ny, nz, plane_c[p], ox, oy, oz, dx, dy, dz, np.float64(f[o + 8 * L + j]))
                px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
                sg = 1.0 if dn < 0.0 else -1.0
                gx, gy, gz = sg * nx, sg * ny, sg * nz
                sx, sy, sz = gx, gy, gz
                if smooth:
                    sx, sy, sz = _shading_normal(vnormal, p, np.float64(f[o + 15 * L + j]),
                                                 np.float64(f[o + 16 * L + j]), sg, gx, gy, gz, dx, dy, dz)
                ob = tri_object[p]
                rho, rs, ns = rho_d[ob], rho_s[ob], n_s[ob]
                path = lpath[j] + t
                if bounce <= 1:
                    lsrc[j] = ob       # the seen object (direct light) or the one that lit it
                if bounce == 0:
                    first_t[ls[j]] = t
                    first_obj[ls[j]] = ob
                    ambient_unit[lq[j]] += lbeta[j] * (rho + rs) * _INV_PI
                ex, ey, ez = emitter_pos[0] - px, emitter_pos[1] - py, emitter_pos[2] - pz
                r = math.sqrt(ex * ex + ey * ey + ez * ez)
                ex, ey, ez = ex / r, ey / r, ez / r
                cs = sx * ex + sy * ey + sz * ez
                ce = -(ex * emitter_axis[0] + ey * emitter_axis[1] + ez * emitter_axis[2])
                if cs > 0.0:
                    if cos_n >= 0.0:
                        bv = _pow(ce, cos_n) if ce > 0.0 else 0.0
                    elif beam_flat:
                        bv = beam_c
                    else:
                        bv = _beam(ce, cos_n, beam)
                    irr = i0 * bv * cs / (r * r)
                else:
                    irr = 0.0
                lw[j] = irr
                lx[j, 0], lx[j, 1], lx[j, 2] = px, py, pz
                lg[j, 0], lg[j, 1], lg[j, 2] = gx, gy, gz
                lsn[j, 0], lsn[j, 1], lsn[j, 2] = sx, sy, sz
                le[j, 0], le[j, 1], le[j, 2] = ex, ey, ez
                lr[j] = r
                lpv[j] = path
                lmat[j, 0], lmat[j, 1], lmat[j, 2] = rho, rs, ns
                if irr > 0.0:
                    # ray j of the shadow packet (the same layout)
                    f[so + j] = np.float32(px + eps * gx)
                    f[so + L + j] = np.float32(py + eps * gy)
                    f[so + 2 * L + j] = np.float32(pz + eps * gz)
                    f[so + 3 * L + j] = 0.0
                    f[so + 4 * L + j] = np.float32(ex)
                    f[so + 5 * L + j] = np.float32(ey)
                    f[so + 6 * L + j] = np.float32(ez)
                    f[so + 7 * L + j] = 0.0
                    f[so + 8 * L + j] = np.float32(r - 2.0 * eps)
                    u[so + 9 * L + j] = INV
                    u[so + 10 * L + j] = 0
                    u[so + 11 * L + j] = 0
                    u[svo + j] = INV
                    shadows += 1
            if shadows:
                eda.rtc_occluded8(sv_addr, scene, s_addr, 0)
                rays += shadows
            for j in range(L):
                if not alive[j]:
                    continue
                dx, dy, dz = ld[j, 0], ld[j, 1], ld[j, 2]
                sx, sy, sz = lsn[j, 0], lsn[j, 1], lsn[j, 2]
                rho, rs, ns = lmat[j, 0], lmat[j, 1], lmat[j, 2]
                if u[svo + j] != 0 and not f[so + 8 * L + j] < 0.0:     # tfar = -inf: blocked
                    w = lbeta[j] * lw[j] * _brdf(rho, rs, ns, sx, sy, sz, le[j, 0], le[j, 1], le[j, 2],
                                                 -dx, -dy, -dz)
                    if bounce == 0:
                        w *= share                   # the group's connection, traced once
                    if w > 0.0:
                        # _accumulate written out: passing it the arrays costs numba's reference
                        # counting per call (an atomic both render threads share: 15 % of a corner render)
                        q = lq[j]
                        length = lpv[j] + lr[j]
                        row = share_row(bounce, lsrc[j], n_obj)
                        power[q] += w
                        for m in range(nk):
                            sn, cs = _sincos(k[m] * length)
                            acc_re[row, m, q] += w * cs
                            acc_im[row, m, q] += w * sn
                        if nbins > 0:
                            b = np.searchsorted(edges, length, side="right") - 1
                            if b >= 0 and b < nbins:
                                trans[q, b] += w
                if bounce == bounces:
                    continue
                s = ls[j]
                ndx, ndy, ndz = _cosine_direction(U[s, 4 + 2 * bounce], U[s, 5 + 2 * bounce], sx, sy, sz)
                gx, gy, gz = lg[j, 0], lg[j, 1], lg[j, 2]
                if ndx * gx + ndy * gy + ndz * gz <= 0.0:    # below the geometric surface
                    alive[j] = False
                    continue
                beta = lbeta[j] * math.pi * _brdf(rho, rs, ns, sx, sy, sz, ndx, ndy, ndz, -dx, -dy, -dz)
                lbeta[j] = beta
                if beta <= 0.0:
                    alive[j] = False
                    continue
                lo[j, 0], lo[j, 1], lo[j, 2] = lx[j, 0] + eps * gx, lx[j, 1] + eps * gy, lx[j, 2] + eps * gz
                ld[j, 0], ld[j, 1], ld[j, 2] = ndx, ndy, ndz
                lpath[j] = lpv[j]
    return rays


@njit(nogil=True, cache=True)
def sobol_digital_shift(sobol, shift, U):  # pragma: no cover
    """``U[i * spp + j, d] = ((sobol[j, d] XOR shift[i, d]) + 1/2) / 2^32``: the same 32-bit
    Sobol' points in every pixel ``i``, digitally shifted by the pixel's random vector. With a
    uniform shift every sample is uniform on the 2^32 grid (cell midpoints) and a pixel's points
    keep the net's stratification."""
    spp, dims = sobol.shape
    for i in range(shift.shape[0]):
        for j in range(spp):
            s = i * spp + j
            for d in range(dims):
                U[s, d] = (np.float64(sobol[j, d] ^ shift[i, d]) + 0.5) * 2.3283064365386963e-10


@njit(nogil=True, cache=True, error_model="numpy")
def subpixel_rays(pixels, spp, width, U, fx, fy, cx, cy, dist, iterations, R, rotate, pix_weight,
                  dirs, beta, fisheye=False, share=1):  # pragma: no cover
    """Sample ``s`` of pixel ``pixels[s // spp]`` through the pixel position ``U[s, 0:2]`` (in
    pixels from the pixel's corner): its unit world direction ``dirs[s]`` (the camera model's
    inversion, :meth:`CameraModel.pixel_rays`, then ``R``) and its weight
    ``beta[s] = pix_weight[pixel] * z^4`` (cos^4 of the camera ray). ``dist``: the lens
    coefficients in OpenCV's order (Brown-Conrady: up to 12, missing ones zero; ``fisheye``:
    k1..k4), or :attr:`CameraModel.kernel_coeffs` (13: the model's reach last);
    ``iterations``: Newton iterations at most. A sample through a point the lens maps
    no ray to (beyond the fold of its model) or 90 degrees or more off axis gets weight 0 (and
    the optical axis as a direction, so Embree sees a finite ray). One pass, operation by
    operation the numpy expressions of the camera model and :func:`rotate_rows` (cos^4 to
    an ulp). ``share > 1`` (a divisor of ``spp``): each group of ``share`` consecutive samples
    of a pixel has one camera position (:func:`render.camera_ray_share`, ``U[s, 0:4]`` the
    same), so the group's first ray is copied to the others instead of computed again."""
    c = np.zeros(13)
    c[12] = math.pi if fisheye else np.inf   # the model's reach, when dist does not give it
    distorted = fisheye
    for j in range(min(dist.shape[0], 13)):
        c[j] = dist[j]
        distorted = distorted or (j < 12 and dist[j] != 0.0)
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    i, s_next, k = -1, 0, 0
    col = row = w = 0.0
    for s in range(U.shape[0]):
        if s == s_next:                  # a new pixel (no integer division per sample)
            i += 1
            s_next += spp
            k = 0
            p = pixels[i]
            col, row = np.float64(p % width), np.float64(p // width)
            w = pix_weight[p]
        if k == share:
            k = 0
        k += 1
        if k > 1:                        # the group's camera ray, computed for its first sample
            dirs[s, 0], dirs[s, 1], dirs[s, 2] = dirs[s - 1, 0], dirs[s - 1, 1], dirs[s - 1, 2]
            beta[s] = beta[s - 1]
            continue
        uu = col + U[s, 0] - 0.5
        vv = row + U[s, 1] - 0.5
        xd = (uu - cx) / fx
        yd = (vv - cy) / fy
        if distorted:
            a, b, c3 = pixel_ray(xd, yd, fisheye, c, iterations)
        else:
            nrm = math.sqrt(xd * xd + yd * yd + 1.0)
            a, b, c3 = xd / nrm, yd / nrm, 1.0 / nrm
        if not (c3 > 0.0):               # no ray (NaN) or none in front of the lens
            a, b, c3 = 0.0, 0.0, 1.0
            beta[s] = 0.0
        else:
            c2 = c3 * c3
            beta[s] = w * (c2 * c2)      # cos^4 (numpy's c**4 and libm's pow differ from it by an ulp)
        if rotate:
            dirs[s, 0] = a * r00 + b * r01 + c3 * r02
            dirs[s, 1] = a * r10 + b * r11 + c3 * r12
            dirs[s, 2] = a * r20 + b * r21 + c3 * r22
        else:
            dirs[s, 0], dirs[s, 1], dirs[s, 2] = a, b, c3


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


# --------------------------------------------------------------------------- dielectrics
#: Specular events (Fresnel reflections and refractions) one camera sample may go through;
#: the reflected branches wait on a stack of this depth. Light still in the path after that
#: many interfaces carries less than R^(k/2) of its power (about 1e-6 for glass): dropped.
MAX_SPECULAR = 24
_STACK = 16
#: A reflected branch with less than this share of its sample's starting weight is not
#: followed (glass of n 1.5: the third internal echo, R^6 = 4e-9, is not): the power it would add
#: is below 1e-6 of the sample's.
_DROP = 1e-6


@njit(nogil=True, cache=True)
def trace_paths_media(scene, buf, org, shared, dirs, path0, beta0, local, U, bounces, normal, plane_c, vnormal,
                      smooth, tri_object, rho_d, rho_s, n_s, ior, sigma_a, sigma_s, hg_g, box_c, box_axes,
                      box_half,
                      emitter_pos, emitter_axis, eps, cos_n, i0,
                      k, acc_re, acc_im, power, ambient_unit, edges, trans, first_t, first_obj):  # pragma: no cover
    """:func:`trace_paths` with smooth dielectric boxes (:mod:`tofhil.sim.dielectric`).

    At a glass face the path splits: the Fresnel reflection ``R`` waits on a stack, the
    refraction ``1 - R`` (Snell) goes on (total internal reflection: the reflection only), so
    a sample follows every specular branch with its exact weight and no extra noise. Inside
    the glass the optical length grows by ``n d`` and the power falls by
    ``exp(-sigma_a d)``. Specular events do not count as bounces: ``bounces`` counts diffuse
    vertices. At a diffuse vertex the emitter is connected straight, or, where the straight
    shadow ray meets a glass box first, along the refracted ray through the two faces of its
    slab (:func:`tofhil.sim.dielectric.slab_link`; its two air legs must be free). Diffuse
    surfaces inside glass are not supported (the parser and the renderer's set-up refuse
    them); a path that still meets one is dropped.
    """
    addr, o = eda.record(buf)
    f = buf
    u = buf.view(np.uint32)
    nk = k.shape[0]
    nbins = edges.shape[0] - 1
    rays = 0
    stk = np.empty((_STACK, 14))
    for s in range(dirs.shape[0]):
        if shared:
            ox, oy, oz = org[0, 0], org[0, 1], org[0, 2]
        else:
            ox, oy, oz = org[s, 0], org[s, 1], org[s, 2]
        dx, dy, dz = dirs[s, 0], dirs[s, 1], dirs[s, 2]
        # (ox, oy, oz) is the path's true vertex, (lx, ly, lz) Embree's lift off its surface:
        # lengths are measured from the vertex, so the lifts add no path.
        lx, ly, lz = 0.0, 0.0, 0.0
        path_in = path0[s]
        beta = beta0[s]
        q = local[s]
        bounce = 0
        inside = -1
        nspec = 0
        primary = True
        sp = 0
        seed = np.uint64(s) * np.uint64(0x632BE59BD9B4E019)
        if U.shape[0] > 0:
            seed = seed ^ np.uint64(U[s, 0] * 4294967296.0)
        ctr = 0
        while True:
            eda.set_ray(f, u, o, np.float32(ox + lx), np.float32(oy + ly), np.float32(oz + lz),
                        np.float32(dx), np.float32(dy), np.float32(dz), np.float32(1e37))
            eda.rtc_intersect1(scene, addr, 0)
            rays += 1
            p = u[o + 17]
            alive = p != eda.INVALID_ID
            if not alive and primary:
                first_t[s] = np.inf
                first_obj[s] = -1
            scattered = False
            if inside >= 0 and sigma_s[inside] > 0.0:
                # ---- a scattering medium: free flight with the extinction sigma_t; a
                # scattering event before the boundary weighs the albedo sigma_s / sigma_t
                md = inside
                sig_t = sigma_a[md] + sigma_s[md]
                dfl = -math.log(1.0 - _dielectric.hash_uniform(seed, ctr)) / sig_t
                ctr += 1
                if dfl < (np.float64(f[o + 8]) if alive else np.inf):
                    scattered = True
                    px, py, pz = ox + dfl * dx, oy + dfl * dy, oz + dfl * dz
                    path = path_in + dfl
                    beta *= sigma_s[md] / sig_t
                    ex, ey, ez = emitter_pos[0] - px, emitter_pos[1] - py, emitter_pos[2] - pz
                    r = math.sqrt(ex * ex + ey * ey + ez * ez)
                    ex, ey, ez = ex / r, ey / r, ez / r
                    w, nr = _medium_link(scene, f, u, o, addr, px, py, pz, ex, ey, ez, r, emitter_axis, eps, cos_n,
                                         i0, box_c[md], box_axes[md], box_half[md], sig_t)
                    rays += nr
                    w *= beta * _dielectric.hg_phase(dx * ex + dy * ey + dz * ez, hg_g[md])
                    if w > 0.0:
                        _accumulate(acc_re, acc_im, power, trans, edges, k, nk, nbins, 0 if bounce == 0 else 1, q, w,
                                    path + r)
                    if bounce == bounces or beta <= 0.0:
                        alive = False
                    else:
                        dx, dy, dz = _dielectric.hg_sample(U[s, 4 + 2 * bounce], U[s, 5 + 2 * bounce], hg_g[md],
                                                           dx, dy, dz)
                        ox, oy, oz = px, py, pz
                        lx, ly, lz = 0.0, 0.0, 0.0
                        path_in = path
                        bounce += 1
                        alive = True
            if alive and not scattered:
                nx, ny, nz = normal[p, 0], normal[p, 1], normal[p, 2]
                t, dn = _plane_hit(normal, plane_c, p, ox, oy, oz, dx, dy, dz, np.float64(f[o + 8]))
                px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
                sg = 1.0 if dn < 0.0 else -1.0
                gx, gy, gz = sg * nx, sg * ny, sg * nz
                ob = tri_object[p]
                if primary:
                    first_t[s] = t
                    first_obj[s] = ob
                    primary = False
                if inside >= 0:
                    path = path_in + ior[inside] * t
                    if sigma_s[inside] == 0.0:          # (a scattering medium's losses: its free flights)
                        beta *= math.exp(-sigma_a[inside] * t)
                else:
                    path = path_in + t
                if ior[ob] > 0.0:
                    # ---- a glass face: Fresnel split
                    if nspec >= MAX_SPECULAR or (inside >= 0 and inside != ob):
                        alive = False                     # (nested glass: refused at set-up)
                    else:
                        nspec += 1
                        n1, n2 = (1.0, ior[ob]) if inside < 0 else (ior[ob], 1.0)
                        ci = abs(dn)
                        refl, ct = _dielectric.fresnel(ci, n1, n2)
                        rx, ry, rz = dx + 2.0 * ci * gx, dy + 2.0 * ci * gy, dz + 2.0 * ci * gz
                        if refl < 1.0:
                            if refl * beta > _DROP * beta0[s] and sp < _STACK:
                                stk[sp, 0], stk[sp, 1], stk[sp, 2] = px, py, pz
                                stk[sp, 3], stk[sp, 4], stk[sp, 5] = rx, ry, rz
                                stk[sp, 6], stk[sp, 7], stk[sp, 8] = path, beta * refl, bounce
                                stk[sp, 9], stk[sp, 10] = inside, nspec
                                stk[sp, 11], stk[sp, 12], stk[sp, 13] = gx, gy, gz
                                sp += 1
                            eta = n1 / n2
                            a = eta * ci - ct
                            dx, dy, dz = eta * dx + a * gx, eta * dy + a * gy, eta * dz + a * gz
                            beta *= 1.0 - refl
                            lx, ly, lz = -eps * gx, -eps * gy, -eps * gz
                            inside = ob if inside < 0 else -1
                        else:                             # total internal reflection
                            dx, dy, dz = rx, ry, rz
                            lx, ly, lz = eps * gx, eps * gy, eps * gz
                        ox, oy, oz = px, py, pz
                        path_in = path
                        continue
                elif inside >= 0:
                    alive = False                         # a diffuse surface inside glass
                else:
                    # ---- a diffuse vertex: as in trace_paths, with the emitter linked through glass
                    sx, sy, sz = gx, gy, gz
                    if smooth:
                        sx, sy, sz = _shading_normal(vnormal, p, np.float64(f[o + 15]), np.float64(f[o + 16]), sg,
                                                     gx, gy, gz, dx, dy, dz)
                    rho, rs, ns = rho_d[ob], rho_s[ob], n_s[ob]
                    if bounce == 0:
                        ambient_unit[q] += beta * (rho + rs) * _INV_PI
                    ex, ey, ez = emitter_pos[0] - px, emitter_pos[1] - py, emitter_pos[2] - pz
                    r = math.sqrt(ex * ex + ey * ey + ez * ez)
                    ex, ey, ez = ex / r, ey / r, ez / r
                    w, extra, nr, gob, kk = _emitter_link(
                        scene, f, u, o, addr, px, py, pz, gx, gy, gz, sx, sy, sz, ex, ey, ez, r, emitter_pos,
                        emitter_axis, eps, cos_n, i0, normal, tri_object, ior, sigma_a, sigma_s, box_c, box_axes,
                        box_half, rho, rs, ns, -dx, -dy, -dz)
                    rays += nr
                    w = beta * w
                    if w > 0.0:
                        _accumulate(acc_re, acc_im, power, trans, edges, k, nk, nbins, 0 if bounce == 0 else 1, q, w,
                                    path + extra)
                    if gob >= 0:                          # the slab's internal echo on the emitter's leg
                        w, extra, nr = _slab_echo(scene, f, u, o, addr, px, py, pz, gx, gy, gz, sx, sy, sz,
                                                  emitter_pos, emitter_axis, eps, cos_n, i0, gob, kk, ior, sigma_a,
                                                  box_c, box_axes, box_half, rho, rs, ns, -dx, -dy, -dz)
                        rays += nr
                        w = beta * w
                        if w > 0.0:
                            _accumulate(acc_re, acc_im, power, trans, edges, k, nk, nbins, 0 if bounce == 0 else 1, q,
                                        w, path + extra)
                    # the emitter's mirror images in the glass faces light this point too
                    for gb in range(ior.shape[0]):
                        if ior[gb] <= 1.0:
                            continue
                        for kk in range(3):
                            for side in (1.0, -1.0):
                                for back in (False, True):
                                    w, extra, nr = _mirror_link(scene, f, u, o, addr, px, py, pz, gx, gy, gz, sx, sy,
                                                                sz, emitter_pos, emitter_axis, eps, cos_n, i0, gb, kk,
                                                                side, back, ior, sigma_a, box_c, box_axes, box_half,
                                                                rho, rs, ns, -dx, -dy, -dz)
                                    rays += nr
                                    w = beta * w
                                    if w > 0.0:
                                        _accumulate(acc_re, acc_im, power, trans, edges, k, nk, nbins,
                                                    0 if bounce == 0 else 1, q, w, path + extra)
                    if bounce == bounces:
                        alive = False
                    else:
                        ndx, ndy, ndz = _cosine_direction(U[s, 4 + 2 * bounce], U[s, 5 + 2 * bounce], sx, sy, sz)
                        if ndx * gx + ndy * gy + ndz * gz <= 0.0:
                            alive = False
                        else:
                            beta = beta * math.pi * _brdf(rho, rs, ns, sx, sy, sz, ndx, ndy, ndz, -dx, -dy, -dz)
                            if beta <= 0.0:
                                alive = False
                            ox, oy, oz = px, py, pz
                            lx, ly, lz = eps * gx, eps * gy, eps * gz
                            dx, dy, dz = ndx, ndy, ndz
                            path_in = path
                            bounce += 1
            if alive:
                continue
            if sp == 0:
                break
            sp -= 1                                       # the next waiting reflection
            ox, oy, oz = stk[sp, 0], stk[sp, 1], stk[sp, 2]
            dx, dy, dz = stk[sp, 3], stk[sp, 4], stk[sp, 5]
            # the reflection leaves on the incoming side: lift along the mirrored direction's normal side
            lx, ly, lz = eps * stk[sp, 11], eps * stk[sp, 12], eps * stk[sp, 13]
            path_in, beta, bounce = stk[sp, 6], stk[sp, 7], int(stk[sp, 8])
            inside, nspec = int(stk[sp, 9]), int(stk[sp, 10])
            primary = False
    return rays


@njit(nogil=True, cache=True)
def _emitter_link(scene, f, u, o, addr, px, py, pz, gx, gy, gz, sx, sy, sz, ex, ey, ez, r, emitter_pos, emitter_axis,
                  eps, cos_n, i0, normal, tri_object, ior, sigma_a, sigma_s, box_c, box_axes, box_half, rho, rs, ns,
                  wox, woy, woz):  # pragma: no cover
    """The emitter's contribution ``f_r E`` at a diffuse vertex (per unit throughput) and the
    optical path from the vertex to the emitter: straight (``E = I cos / r^2``), or through the
    slab of the glass box the straight shadow ray meets first; the rays it traced; and the
    glass box and its slab axis where that slab link exists (else -1, 0), for
    :func:`_slab_echo`."""
    cs = sx * ex + sy * ey + sz * ez
    ce = -(ex * emitter_axis[0] + ey * emitter_axis[1] + ez * emitter_axis[2])
    if not (cs > 0.0 and ce > 0.0):
        return 0.0, r, 0, -1, 0
    ax, ay, az = px + eps * gx, py + eps * gy, pz + eps * gz
    eda.set_ray(f, u, o, np.float32(ax), np.float32(ay), np.float32(az),
                np.float32(ex), np.float32(ey), np.float32(ez), np.float32(r - 2.0 * eps))
    eda.rtc_intersect1(scene, addr, 0)
    hp = u[o + 17]
    if hp == eda.INVALID_ID:
        irr = i0 * _pow(ce, cos_n) * cs / (r * r)
        return irr * _brdf(rho, rs, ns, sx, sy, sz, ex, ey, ez, wox, woy, woz), r, 1, -1, 0
    gob = tri_object[hp]
    if ior[gob] <= 0.0:
        return 0.0, r, 1, -1, 0                                  # blocked by an opaque object
    if ior[gob] == 1.0:
        # an index-matched box (a medium): the straight ray, its extinction over the chord
        t0, t1 = _dielectric.box_chord(px, py, pz, ex, ey, ez, r, box_c[gob], box_axes[gob], box_half[gob])
        tr = math.exp(-(sigma_a[gob] + sigma_s[gob]) * max(0.0, t1 - t0))
        eda.set_ray(f, u, o, np.float32(px + (t1 + eps) * ex), np.float32(py + (t1 + eps) * ey),
                    np.float32(pz + (t1 + eps) * ez), np.float32(ex), np.float32(ey), np.float32(ez),
                    np.float32(r - t1 - 2.0 * eps))
        eda.rtc_occluded1(scene, addr, 0)
        if f[o + 8] < 0.0:
            return 0.0, r, 2, -1, 0
        irr = i0 * _pow(ce, cos_n) * cs / (r * r) * tr
        return irr * _brdf(rho, rs, ns, sx, sy, sz, ex, ey, ez, wox, woy, woz), r, 2, -1, 0
    # The face it met picks the slab: the box axis along that face's normal.
    kk = 0
    best = -1.0
    for j in range(3):
        d = abs(normal[hp, 0] * box_axes[gob, j, 0] + normal[hp, 1] * box_axes[gob, j, 1]
                + normal[hp, 2] * box_axes[gob, j, 2])
        if d > best:
            best, kk = d, j
    ok, ux, uy, uz, d1, d3, x2, y2, z2, tf, geo, opl = _dielectric.slab_link(
        px, py, pz, emitter_pos[0], emitter_pos[1], emitter_pos[2], box_c[gob], box_axes[gob], box_half[gob], kk,
        ior[gob], sigma_a[gob])
    if not ok:
        return 0.0, r, 1, -1, 0
    cs = sx * ux + sy * uy + sz * uz
    ce = -(ux * emitter_axis[0] + uy * emitter_axis[1] + uz * emitter_axis[2])
    if not (cs > 0.0 and ce > 0.0 and ux * gx + uy * gy + uz * gz > 0.0):
        return 0.0, r, 1, -1, 0
    # both air legs free (the slab's own faces end them)
    eda.set_ray(f, u, o, np.float32(ax), np.float32(ay), np.float32(az),
                np.float32(ux), np.float32(uy), np.float32(uz), np.float32(d1 - 2.0 * eps))
    eda.rtc_occluded1(scene, addr, 0)
    if f[o + 8] < 0.0:
        return 0.0, r, 2, -1, 0
    eda.set_ray(f, u, o, np.float32(x2 + eps * ux), np.float32(y2 + eps * uy), np.float32(z2 + eps * uz),
                np.float32(ux), np.float32(uy), np.float32(uz), np.float32(d3 - 2.0 * eps))
    eda.rtc_occluded1(scene, addr, 0)
    if f[o + 8] < 0.0:
        return 0.0, r, 3, -1, 0
    w = i0 * _pow(ce, cos_n) * tf * geo * cs * _brdf(rho, rs, ns, sx, sy, sz, ux, uy, uz, wox, woy, woz)
    return w, opl, 3, gob, kk


@njit(nogil=True, cache=True)
def _slab_echo(scene, f, u, o, addr, px, py, pz, gx, gy, gz, sx, sy, sz, emitter_pos, emitter_axis, eps, cos_n, i0,
               gob, kk, ior, sigma_a, box_c, box_axes, box_half, rho, rs, ns, wox, woy, woz):  # pragma: no cover
    """The emitter's light at a diffuse vertex after crossing glass box ``gob``'s slab with
    two internal reflections (enter, reflect off the far face, off the near face, leave):
    unfolded, a slab three times as thick to the emitter moved 2T farther along the slab's
    normal, times the two internal Fresnel reflectances. ``(f_r E, opl, rays)``."""
    mx, my, mz = box_axes[gob, kk, 0], box_axes[gob, kk, 1], box_axes[gob, kk, 2]
    c = box_c[gob]
    sgn = 1.0 if (emitter_pos[0] - px) * mx + (emitter_pos[1] - py) * my + (emitter_pos[2] - pz) * mz > 0.0 else -1.0
    thick = 2.0 * box_half[gob, kk]
    # the unfolded slab: from the near face, 3T thick; its centre T beyond the real one
    vc = np.empty(3)
    vc[0], vc[1], vc[2] = c[0] + sgn * thick * mx, c[1] + sgn * thick * my, c[2] + sgn * thick * mz
    vh = box_half[gob].copy()
    vh[kk] = 1.5 * thick
    ex = emitter_pos[0] + 2.0 * sgn * thick * mx
    ey = emitter_pos[1] + 2.0 * sgn * thick * my
    ez = emitter_pos[2] + 2.0 * sgn * thick * mz
    ok, ux, uy, uz, d1, d3, x2, y2, z2, tf, geo, opl = _dielectric.slab_link(
        px, py, pz, ex, ey, ez, vc, box_axes[gob], vh, kk, ior[gob], sigma_a[gob])
    if not ok:
        return 0.0, opl, 0
    cs = sx * ux + sy * uy + sz * uz
    ce = -(ux * emitter_axis[0] + uy * emitter_axis[1] + uz * emitter_axis[2])
    if not (cs > 0.0 and ce > 0.0 and ux * gx + uy * gy + uz * gz > 0.0):
        return 0.0, opl, 0
    st = math.sqrt(max(0.0, 1.0 - (abs(ux * mx + uy * my + uz * mz)) ** 2)) / ior[gob]
    ri, _ = _dielectric.fresnel(math.sqrt(1.0 - st * st), ior[gob], 1.0)
    # the air legs: the first is the direct link's; the last leaves the real far face
    x2, y2, z2 = x2 - 2.0 * sgn * thick * mx, y2 - 2.0 * sgn * thick * my, z2 - 2.0 * sgn * thick * mz
    eda.set_ray(f, u, o, np.float32(px + eps * gx), np.float32(py + eps * gy), np.float32(pz + eps * gz),
                np.float32(ux), np.float32(uy), np.float32(uz), np.float32(d1 - 2.0 * eps))
    eda.rtc_occluded1(scene, addr, 0)
    if f[o + 8] < 0.0:
        return 0.0, opl, 1
    eda.set_ray(f, u, o, np.float32(x2 + eps * ux), np.float32(y2 + eps * uy), np.float32(z2 + eps * uz),
                np.float32(ux), np.float32(uy), np.float32(uz), np.float32(d3 - 2.0 * eps))
    eda.rtc_occluded1(scene, addr, 0)
    if f[o + 8] < 0.0:
        return 0.0, opl, 2
    irr = i0 * _pow(ce, cos_n) * tf * ri * ri * geo * cs
    return irr * _brdf(rho, rs, ns, sx, sy, sz, ux, uy, uz, wox, woy, woz), opl, 2


@njit(nogil=True, cache=True)
def _medium_link(scene, f, u, o, addr, px, py, pz, ex, ey, ez, r, emitter_axis, eps, cos_n, i0, centre, axes, half,
                 sig_t):  # pragma: no cover
    """The emitter's intensity over distance squared at a scattering point inside a medium
    box, times the extinction to the box's boundary (the phase function is the caller's),
    and the rays traced: the straight link, free beyond the box."""
    ce = -(ex * emitter_axis[0] + ey * emitter_axis[1] + ez * emitter_axis[2])
    if not ce > 0.0:
        return 0.0, 0
    _, t1 = _dielectric.box_chord(px, py, pz, ex, ey, ez, r, centre, axes, half)
    eda.set_ray(f, u, o, np.float32(px + (t1 + eps) * ex), np.float32(py + (t1 + eps) * ey),
                np.float32(pz + (t1 + eps) * ez), np.float32(ex), np.float32(ey), np.float32(ez),
                np.float32(r - t1 - 2.0 * eps))
    eda.rtc_occluded1(scene, addr, 0)
    if f[o + 8] < 0.0:
        return 0.0, 1
    return i0 * _pow(ce, cos_n) / (r * r) * math.exp(-sig_t * t1), 1


@njit(nogil=True, cache=True)
def _mirror_link(scene, f, u, o, addr, px, py, pz, gx, gy, gz, sx, sy, sz, emitter_pos, emitter_axis, eps, cos_n, i0,
                 gb, kk, side, back, ior, sigma_a, box_c, box_axes, box_half, rho, rs, ns,
                 wox, woy, woz):  # pragma: no cover
    """The emitter's light at a diffuse vertex by a reflection in glass box ``gb``'s face
    ``side * axis kk``: off the face itself (``back`` False: the emitter's mirror image,
    ``R I / L^2``), or entering it, reflected off the opposite face inside and leaving it
    again (``back`` True: unfolded, a slab twice as thick to the emitter mirrored in the
    opposite face; ``T_F R_i G``). Both the vertex and the emitter must be on the face's outer
    side. ``(f_r E, opl, rays)``."""
    mx, my, mz = side * box_axes[gb, kk, 0], side * box_axes[gb, kk, 1], side * box_axes[gb, kk, 2]
    hk = box_half[gb, kk]
    cx, cy, cz = box_c[gb, 0] + hk * mx, box_c[gb, 1] + hk * my, box_c[gb, 2] + hk * mz     # on the face
    hx = (px - cx) * mx + (py - cy) * my + (pz - cz) * mz
    he = (emitter_pos[0] - cx) * mx + (emitter_pos[1] - cy) * my + (emitter_pos[2] - cz) * mz
    if hx <= 0.0 or he <= 0.0:
        return 0.0, 0.0, 0
    n = ior[gb]
    if not back:
        ex, ey, ez = emitter_pos[0] - 2.0 * he * mx, emitter_pos[1] - 2.0 * he * my, emitter_pos[2] - 2.0 * he * mz
        vx, vy, vz = ex - px, ey - py, ez - pz
        L = math.sqrt(vx * vx + vy * vy + vz * vz)
        vx, vy, vz = vx / L, vy / L, vz / L
        d1 = L * hx / (hx + he)
        hx_, hy_, hz_ = px + d1 * vx, py + d1 * vy, pz + d1 * vz
        for j in range(3):
            if j != kk:
                a = ((hx_ - box_c[gb, 0]) * box_axes[gb, j, 0] + (hy_ - box_c[gb, 1]) * box_axes[gb, j, 1]
                     + (hz_ - box_c[gb, 2]) * box_axes[gb, j, 2])
                if abs(a) > box_half[gb, j]:
                    return 0.0, 0.0, 0
        refl, _ = _dielectric.fresnel((hx + he) / L, 1.0, n)
        weight, geo, opl = refl, 1.0 / (L * L), L
        d3 = L - d1
        ox, oy, oz = hx_, hy_, hz_
    else:
        bx, by, bz = box_c[gb, 0] - hk * mx, box_c[gb, 1] - hk * my, box_c[gb, 2] - hk * mz  # the opposite face
        hb = (emitter_pos[0] - bx) * mx + (emitter_pos[1] - by) * my + (emitter_pos[2] - bz) * mz
        ex, ey, ez = emitter_pos[0] - 2.0 * hb * mx, emitter_pos[1] - 2.0 * hb * my, emitter_pos[2] - 2.0 * hb * mz
        vc = np.empty(3)
        vc[0], vc[1], vc[2] = bx, by, bz
        vh = box_half[gb].copy()
        vh[kk] = 2.0 * hk
        ok, vx, vy, vz, d1, d3, x2, y2, z2, tf, geo, opl = _dielectric.slab_link(
            px, py, pz, ex, ey, ez, vc, box_axes[gb], vh, kk, n, sigma_a[gb])
        if not ok:
            return 0.0, 0.0, 0
        st = math.sqrt(max(0.0, 1.0 - (vx * mx + vy * my + vz * mz) ** 2)) / n
        ri, _ = _dielectric.fresnel(math.sqrt(1.0 - st * st), n, 1.0)
        weight = tf * ri
        hb2 = (x2 - bx) * mx + (y2 - by) * my + (z2 - bz) * mz       # the real exit: mirrored back
        ox, oy, oz = x2 - 2.0 * hb2 * mx, y2 - 2.0 * hb2 * my, z2 - 2.0 * hb2 * mz
    # the last leg runs along the mirrored direction to the real emitter
    vn = vx * mx + vy * my + vz * mz
    lx, ly, lz = vx - 2.0 * vn * mx, vy - 2.0 * vn * my, vz - 2.0 * vn * mz
    cs = sx * vx + sy * vy + sz * vz
    ce = -(lx * emitter_axis[0] + ly * emitter_axis[1] + lz * emitter_axis[2])
    if not (cs > 0.0 and ce > 0.0 and vx * gx + vy * gy + vz * gz > 0.0 and weight > 0.0):
        return 0.0, 0.0, 0
    eda.set_ray(f, u, o, np.float32(px + eps * gx), np.float32(py + eps * gy), np.float32(pz + eps * gz),
                np.float32(vx), np.float32(vy), np.float32(vz), np.float32(d1 - 2.0 * eps))
    eda.rtc_occluded1(scene, addr, 0)
    if f[o + 8] < 0.0:
        return 0.0, 0.0, 1
    eda.set_ray(f, u, o, np.float32(ox + eps * lx), np.float32(oy + eps * ly), np.float32(oz + eps * lz),
                np.float32(lx), np.float32(ly), np.float32(lz), np.float32(d3 - 2.0 * eps))
    eda.rtc_occluded1(scene, addr, 0)
    if f[o + 8] < 0.0:
        return 0.0, 0.0, 2
    irr = i0 * _pow(ce, cos_n) * weight * geo * cs
    return irr * _brdf(rho, rs, ns, sx, sy, sz, vx, vy, vz, wox, woy, woz), opl, 2


# (the kernels above inline the lens models and the dielectric and Embree helpers: their cache
# is dropped when those sources change, which numba's own cache key does not see)
_drop_stale_cache(subpixel_rays, [_camera_kernels.__file__, _lens_models.__file__, _dielectric.__file__, eda.__file__])
