"""The generated code's own tanh (`torchfric.accel.native.tanh`) against the C library's.

Truth is the C library's ``tanh``, called from the same compiled file. The scalar form (one
member at a time) and the SIMD form (four members per vector) give the same bits as each other
on every input, so a member's numbers do not depend on the batch it runs in. Where the C library
is the one the forms were written after (glibc 2.36 on x86-64, this project's machines) they
also give its bits on every input, so the filter's numbers did not move when tanh became its
own; elsewhere both stay within 2 units in the last place of that library's tanh.
"""

from __future__ import annotations

import ctypes
import platform

import numpy as np
import pytest

from torchfric.accel import native
from torchfric.accel.native.cache import _build
from torchfric.accel.native.emit import _HEADER, _vector_prelude
from torchfric.accel.native.tanh import SCALAR

pytestmark = pytest.mark.skipif(native.compiler() is None, reason="no C compiler here")

# The generated code's entry point, `torchfric_chunk`, with m0 choosing the form: 0 the scalar,
# 1 the SIMD, 2 the C library's; p = (x, out), C = the count (a multiple of 4).
_LIB = "\n".join([*_HEADER, SCALAR, *_vector_prelude(4), """
void torchfric_chunk(int64_t m0, int64_t m1, int64_t K, int64_t C, void **p) {
  (void)m1; (void)K;
  const double *x = p[0];
  double *out = p[1];
  for (int64_t i = 0; i < C; i += 4) {
    if (m0 == 1) {
      vd a; memcpy(&a, x + i, sizeof a);
      const vd r = v_tanh(a);
      memcpy(out + i, &r, sizeof r);
    } else for (int l = 0; l < 4; ++l) out[i + l] = m0 == 0 ? tf_tanh(x[i + l]) : tanh(x[i + l]);
  }
}
"""])  # fmt: skip
_FORMS = {"scalar": 0, "simd": 1, "libm": 2}


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("TORCHFRIC_CACHE", str(tmp_path / "cache"))


def _inputs(n: int) -> np.ndarray:
    """Every kind of double: any bit pattern (NaNs, infinities, subnormals), magnitudes from
    2^-60 to 2^6 of both signs (each branch of the algorithm: |x| < 2^-55, the polynomial alone,
    k = −1, −2, −3 below 1; k = 3 … 64 above it; the saturated range from 22), evenly spread
    values in ±30, and the branch boundaries themselves with their neighbours."""
    g = np.random.default_rng(7)
    bits = g.integers(0, 2**63, n, dtype=np.int64) * g.choice([1, -1], n)
    mags = np.exp2(g.uniform(-60.0, 6.0, n)) * g.choice([-1.0, 1.0], n)
    spread = g.uniform(-30.0, 30.0, n)
    edges = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1.0, 22.0, 2.0**-55, 2.0**-56,
                      0.17328679513998632, 0.519860385419959, 19.06, 6.93, 5e-324, 1e-300])  # fmt: skip
    edges = np.concatenate([edges, -edges])
    near = np.concatenate([np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf)])
    x = np.concatenate([bits.view(np.float64), mags, spread, edges, near])
    return np.ascontiguousarray(x[: len(x) // 4 * 4])


def _call(lib: ctypes.CDLL, form: str, x: np.ndarray) -> np.ndarray:
    out = np.empty_like(x)
    p = (ctypes.c_void_p * 2)(x.ctypes.data, out.ctypes.data)
    i64 = ctypes.c_int64
    lib.torchfric_chunk(i64(_FORMS[form]), i64(0), i64(0), i64(len(x)), p)
    return out


def _same_bits(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Equal to the bit, or both NaN (a NaN's payload is the platform's business)."""
    return (a.view(np.int64) == b.view(np.int64)) | (np.isnan(a) & np.isnan(b))


def _reference_libm() -> bool:
    """The C library the forms were written after: glibc 2.36 on x86-64."""
    name, version = platform.libc_ver()
    return platform.machine() in ("x86_64", "AMD64") and name == "glibc" and version == "2.36"


def test_scalar_and_simd_tanh_give_the_same_bits_and_the_c_librarys() -> None:
    lib, _ = _build(_LIB, native.compiler())  # type: ignore[arg-type]
    x = _inputs(1_000_000)
    scalar, vector, libm = (_call(lib, f, x) for f in ("scalar", "simd", "libm"))
    differ = ~_same_bits(scalar, vector)
    assert not differ.any(), f"scalar and SIMD tanh differ at x = {x[differ][:5]}"
    finite = np.isfinite(libm)
    assert _same_bits(np.where(finite, 0.0, scalar), np.where(finite, 0.0, libm)).all()
    assert np.array_equal(np.signbit(scalar), np.signbit(libm))  # tanh(±0) = ±0, odd everywhere
    if _reference_libm():
        differ = ~_same_bits(scalar, libm)
        assert not differ.any(), f"{differ.sum()} inputs differ from glibc, e.g. {x[differ][:5]}"
    else:
        ulp = np.spacing(np.abs(libm[finite]))
        assert np.max(np.abs(scalar[finite] - libm[finite]) / ulp) <= 2.0
    assert np.array_equal(scalar, -_call(lib, "scalar", -x), equal_nan=True)  # odd
