"""The synthetic rig's LuGre integrator as C: the sub-step loop of
`torchfric.data.rig_model._integrate`, statement for statement, built and cached like the
filter's generated code (`torchfric.accel.native.cache`).

The Python loop costs about 0.1 s per 30-second record (a third of a warm quick start, which
simulates three); this one about a millisecond. The numbers are the same to the bit: the same
IEEE operations in the same order (C's ``a * b * c`` and Python's both group from the left; the
compiler may not contract into FMAs, ``-ffp-contract=off``, nor reorder, no fast-math), the
same libm ``exp`` and ``expm1`` that Python's math module calls, and the constants computed
once in Python (`torchfric.data.rig_model.integrator_constants`). tests/test_rig.py holds the two to exact equality on
whole records. Without a C compiler, or with ``TORCHFRIC_NATIVE=0``, `lugre_integrator` gives
None and the rig runs the Python loop.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import numpy as np

from .cache import _build
from .scalar import NativeUnavailable

__all__ = ["lugre_integrator"]

# p[0] c_m·u, p[1] τ_d, p[2] the constants of `integrator_constants` then q0, v0, z0,
# p[3..5] q, v, z out; n samples, `ns` sub-steps each (in the constants' tail).
_SOURCE = r"""
#include <math.h>
#include <stdint.h>

void torchfric_chunk(int64_t a, int64_t b, int64_t K, int64_t n, void **p) {
    const double *cmu = (const double *)p[0], *dist = (const double *)p[1];
    const double *c = (const double *)p[2];
    double *qs = (double *)p[3], *vs = (double *)p[4], *zs = (double *)p[5];
    const double h = c[0], Fc = c[2], dF = c[3], ivs = c[4], s1 = c[6], hs0 = c[7];
    const double hhs0 = c[8], s1h = c[9], hh = c[10], m_num = c[11], den0 = c[12];
    const int64_t ns = (int64_t)c[13];
    double q = c[14], v = c[15], z = c[16], dv = 0.0;
    (void)a; (void)b; (void)K;
    if (n < 1) return;
    qs[0] = q; vs[0] = v; zs[0] = z;
    for (int64_t k = 0; k < n - 1; k++) {
        const double hf = h * (cmu[k] + dist[k]);
        for (int64_t s = 0; s < ns; s++) {
            const double vm = v + 0.5 * dv;
            const double w = vm * ivs;
            const double x = hs0 * (vm >= 0.0 ? vm : -vm) / (Fc + dF * exp(-w * w));
            double ph, E, ps, ch;
            if (x < 1e-2) {
                ph = 1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x / 120.0)));
                E = 1.0 - x * ph;
                ps = 0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x * (1.0 / 120.0 - x / 720.0)));
                ch = 1.0 / 6.0 - x * (1.0 / 24.0 - x * (1.0 / 120.0 - x * (1.0 / 720.0 - x / 5040.0)));
            } else {
                const double em1 = expm1(-x);
                E = 1.0 + em1;
                ph = -em1 / x;
                ps = (1.0 - ph) / x;
                ch = (0.5 - ps) / x;
            }
            const double vh = v * h;
            const double z_mean0 = z * ph + vh * (ps - ch);
            const double dz0 = z * (E - 1.0) + vh * (ph - ps);
            const double v1 = (m_num * v + hf - hs0 * z_mean0 - s1 * dz0) / (den0 + hhs0 * ch + s1h * ps);
            z += dz0 + v1 * h * ps;
            q += hh * (v + v1);
            dv = v1 - v;
            v = v1;
        }
        qs[k + 1] = q; vs[k + 1] = v; zs[k + 1] = z;
    }
}
"""


def lugre_integrator() -> Callable | None:
    """The rig's `torchfric.data.rig_model.Integrator` as compiled C, or None where it cannot
    be had (no C compiler, ``TORCHFRIC_NATIVE=0``, the build failing: the rig then runs its
    Python loop, to the same numbers)."""
    from . import _enabled, compiler  # (the package imports this module's siblings first)

    cc = compiler()
    if cc is None or not _enabled():
        return None
    try:
        lib, _ = _build(_SOURCE, cc)
    except NativeUnavailable:
        return None

    def integrate(cmu, dist, constants, substeps, q, v, z):  # type: ignore[no-untyped-def]
        n = len(cmu)
        consts = np.array([*constants, float(substeps), q, v, z], dtype=np.float64)
        arrays = [np.ascontiguousarray(cmu, dtype=np.float64),
                  np.ascontiguousarray(dist, dtype=np.float64), consts,
                  np.empty(n), np.empty(n), np.empty(n)]  # fmt: skip
        ptrs = (ctypes.c_void_p * 6)(*[a.ctypes.data for a in arrays])
        lib.torchfric_chunk(0, 1, 1, n, ptrs)
        return arrays[3], arrays[4], arrays[5]

    return integrate
