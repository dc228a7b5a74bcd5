"""Compiled loops for the embree build path (numba), beside the numpy code they replace.

The build's float32 rays, the hit test and the float64 ranges are made here in one pass per
block of rays instead of ~15 numpy passes, and the angular boxes' float32 screen in one pass
per sample (docs/SCALE.md, "Where the build's time goes"). Every float64 operation is the numpy
code's, operand for operand and in the same order: products and sums of two operands only,
each rounded (numba contracts nothing into an FMA without ``fastmath``, which is never set
here; the test reads the generated machine code), conversions to float32 round to nearest as numpy's
``astype`` does, and the sines and cosines stay in numpy (a compiled ``sin`` need not be the
one numpy calls): the kernels only multiply, add, divide and take square roots, which IEEE 754
rounds one way. ``tests/test_ray_kernel.py`` checks that both paths give the same bytes.

numba is optional (the ``sim`` extra installs it): without it the numpy code runs, same bytes,
slower. Loading numba costs a process about 0.5 s (its import, then the first call reading the
cache), so a process starts on numpy and loads the kernels once it has cast
:data:`SWITCH_RAYS` rays (a build: within its first two real shards; ``apcg simulate`` of a few
conditions: never). ``APCG_KERNELS`` in the environment overrides that: ``numpy`` never loads
them, ``compiled`` loads them at the first call. Compiled code is cached beside this file
(``__pycache__``; numba's per-user cache where that is read-only): the first process on a
machine, or the first after this file changes, compiles for ~2.5 s instead of reading it.
"""

from __future__ import annotations

import numpy as np

from apcg_core.kernel_loader import ENV, KernelSet, Loader

__all__ = ["ENV", "SWITCH_RAYS", "enabled", "expect", "loaded", "require",
           "use_for"]
# Rays a process casts on the numpy path before it loads the kernels: the numpy path's extra
# cost over them (~75 ns a ray) is then about the ~0.5 s that loading costs (rent, then buy).
SWITCH_RAYS = 4_000_000

# the one loader of the core's compiled sets (apcg_core/kernel_loader.py); _compile is below
_loader = Loader(lambda: _compile(), "the compiled ray kernels", SWITCH_RAYS)
enabled, loaded, use_for, require, expect = (_loader.enabled, _loader.loaded,
                                             _loader.use_for, _loader.require, _loader.expect)


def _compile() -> KernelSet:
    from numba import njit

    jit = njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)

    @jit
    def row_elevations(nh, h_lo, beta0, r_beta, beta):
        """Elevation of every box row, sample by sample: beta0 + h r_beta, as rays._block."""
        r = 0
        for s in range(nh.shape[0]):
            for j in range(nh[s]):
                x = np.float64(h_lo[s] + j) * r_beta
                beta[r] = beta0[s] + x
                r += 1

    @jit
    def block_rays(start, stop, row, nw, nh, w_lo, w_min, sin_a, cos_a, sin_b, cos_b, m,
                   t_start, lidar_body, u, origin, direction):
        """Rays of samples [start, stop), whose first box row is ``row``: sample by sample,
        row (h) by row, column (w) by column, as rays._block makes them. sin_b / cos_b are
        per box row; u is scratch for one sample's column factors. Returns the ray count."""
        k = 0
        for s in range(start, stop):
            m00, m01, m02 = m[s, 0, 0], m[s, 0, 1], m[s, 0, 2]
            m10, m11, m12 = m[s, 1, 0], m[s, 1, 1], m[s, 1, 2]
            m20, m21, m22 = m[s, 2, 0], m[s, 2, 1], m[s, 2, 2]
            ts = t_start[s]
            l0, l1, l2 = lidar_body[s, 0], lidar_body[s, 1], lidar_body[s, 2]
            ncol = nw[s]
            iw0 = w_lo[s] - w_min
            for i in range(ncol):  # the column's factor u = sa M[0] + ca M[2] (rows of M)
                sa = sin_a[iw0 + i]
                ca = cos_a[iw0 + i]
                p = sa * m00
                q = ca * m20
                u[i, 0] = p + q
                p = sa * m01
                q = ca * m21
                u[i, 1] = p + q
                p = sa * m02
                q = ca * m22
                u[i, 2] = p + q
            for _ in range(nh[s]):
                cb = cos_b[row]
                sb = sin_b[row]
                row += 1
                e0 = sb * m10
                e1 = sb * m11
                e2 = sb * m12
                for i in range(ncol):  # d = cb u + sb M[1]; origin = t_start d - M^T C
                    d = cb * u[i, 0]
                    d = d + e0
                    direction[k, 0] = np.float32(d)
                    d = d * ts
                    origin[k, 0] = np.float32(d - l0)
                    d = cb * u[i, 1]
                    d = d + e1
                    direction[k, 1] = np.float32(d)
                    d = d * ts
                    origin[k, 1] = np.float32(d - l1)
                    d = cb * u[i, 2]
                    d = d + e2
                    direction[k, 2] = np.float32(d)
                    d = d * ts
                    origin[k, 2] = np.float32(d - l2)
                    k += 1
        return k

    @jit
    def block_hits(start, stop, nw, nh, w_lo, h_lo, t_start, t32, direction, limit32,
                   hit_limit, out_s, out_w, out_h, out_r, n):
        """The hits of a block's embree answers t32, appended to out_* from index n: sample,
        w, h and float64 range t_start + t |d|, as EmbreeCaster.cast_hits and RayBlock.cells
        give them. Returns the new count."""
        k = 0
        for s in range(start, stop):
            ts = t_start[s]
            w0 = w_lo[s]
            ncol = nw[s]
            for j in range(nh[s]):
                for i in range(ncol):
                    t = t32[k + i]
                    if t < limit32:
                        dx = np.float64(direction[k + i, 0])
                        dy = np.float64(direction[k + i, 1])
                        dz = np.float64(direction[k + i, 2])
                        xx = dx * dx
                        yy = dy * dy
                        zz = dz * dz
                        norm = np.sqrt((xx + yy) + zz)
                        tt = np.float64(t) * norm
                        if tt < hit_limit:
                            out_s[n] = s
                            out_w[n] = w0 + i
                            out_h[n] = h_lo[s] + j
                            out_r[n] = ts + tt
                            n += 1
                k += ncol
        return n

    @jit
    def screen(v32, m32, c32, scale, tol, ns, vs, ta, tb):
        """rays._angle_extremes' float32 screen: the (sample, vertex) pairs within the band of
        each sample's extreme azimuth and elevation ratios (x / z and y / hypot(x, z)), the
        band being tol * scale for azimuth and tol * (scale + max |ratio|) for elevation,
        written to ns / vs in row-major order. v32 is (3, V): x, y, z rows, so that the ratios'
        loop runs in SIMD lanes. ta / tb: scratch for one sample's ratios. Returns the number
        of pairs."""
        n = m32.shape[0]
        nv = v32.shape[1]
        vx = v32[0]
        vy = v32[1]
        vz = v32[2]
        k = 0
        for s in range(n):
            a0, a1, a2 = m32[s, 0, 0], m32[s, 0, 1], m32[s, 0, 2]
            b0, b1, b2 = m32[s, 1, 0], m32[s, 1, 1], m32[s, 1, 2]
            g0, g1, g2 = m32[s, 2, 0], m32[s, 2, 1], m32[s, 2, 2]
            cy = c32[s, 1]
            cz = c32[s, 2]
            for v in range(nv):
                x = a0 * vx[v] + a1 * vy[v] + a2 * vz[v]
                y = b0 * vx[v] + b1 * vy[v] + b2 * vz[v] + cy
                z = g0 * vx[v] + g1 * vy[v] + g2 * vz[v] + cz
                ta[v] = x / z
                tb[v] = y / np.sqrt(x * x + z * z)
            a_max = ta[0]
            a_min = ta[0]
            b_max = tb[0]
            b_min = tb[0]
            for v in range(1, nv):
                a_max = max(a_max, ta[v])
                a_min = min(a_min, ta[v])
                b_max = max(b_max, tb[v])
                b_min = min(b_min, tb[v])
            la = tol * scale[s]
            lb = tol * (scale[s] + max(abs(b_max), abs(b_min)))
            a_hi, a_lo = a_max - la, a_min + la
            b_hi, b_lo = b_max - lb, b_min + lb
            for v in range(nv):
                ra = ta[v]
                rb = tb[v]
                if ra >= a_hi or ra <= a_lo or rb >= b_hi or rb <= b_lo:
                    ns[k] = s
                    vs[k] = v
                    k += 1
        return k

    return KernelSet(row_elevations=row_elevations, rays=block_rays, hits=block_hits,
                     screen=screen)
