"""tanh for the generated CPU code: one algorithm, in scalar and in SIMD form.

A tanh network's step calls tanh a dozen times a sample (three neurons, four RK4 stages). The C
library's tanh is a function of one double, so the SIMD program called it lane by lane: at the
default 9-member ensemble those calls were about a third of the step. `SCALAR` and `vector(w)`
are tanh written out in C — `tf_tanh(double)` and `v_tanh(vd)` — by the algorithm of the C
library this project runs on (glibc's, from fdlibm: tanh from expm1 with expm1's argument reduced
by k·ln 2 and a rational approximation on the reduced range), operation for operation, so that
the two forms give the same bits as each other on every machine, and the same bits as glibc's
own tanh where glibc is the one measured here (2.36, x86-64): the generated code's numbers did
not move when its tanh became its own (tested over millions of inputs where the C library is
that one, and scalar against SIMD everywhere).

glibc selects at run time an expm1 compiled with fused multiply-adds on CPUs with FMA and AVX2;
the code here does the same at compile time (`-march=native`): `TF_FMA` is then `fma`, at the
places where that build fuses (read from its machine code), else a product and a sum. The SIMD
form evaluates every branch of the scalar one and selects per lane; out-of-range shift counts
are masked, so no lane's discarded branch is undefined behaviour. Only the CPU code uses these:
the CUDA kernel keeps CUDA's tanh and the exported C (`torchfric.export`) the C library's.
"""

from __future__ import annotations

__all__ = ["SCALAR", "vector"]

# fdlibm's constants (exact decimal forms of the binary64 values).
_LN2_HI, _LN2_LO = "6.93147180369123816490e-01", "1.90821492927058770002e-10"
_INV_LN2 = "1.44269504088896338700e+00"
_Q = ("-3.33333333333331316428e-02", "1.58730158725481460165e-03", "-7.93650757867487942473e-05",
      "4.00821782732936239552e-06", "-2.01099218183624371326e-07")  # fmt: skip

SCALAR = f"""\
#if defined(__FMA__) && defined(__AVX2__)
#define TF_FMA(a, b, c) fma((a), (b), (c))
#else
#define TF_FMA(a, b, c) ((a) * (b) + (c))
#endif
static inline int64_t tf_bits(double d) {{ int64_t b; memcpy(&b, &d, 8); return b; }}
static inline double tf_double(int64_t b) {{ double d; memcpy(&d, &b, 8); return d; }}
static inline double tf_tanh(double x) {{
  const int64_t b = tf_bits(x), ix = (b >> 32) & 0x7fffffff;
  if (ix >= 0x7ff00000) return b >= 0 ? 1.0 / x + 1.0 : 1.0 / x - 1.0;
  if (ix < 0x3c800000) return x * (1.0 + x);
  double z = 1.0 - 1.0e-300;
  if (ix < 0x40360000) {{
    const int ge1 = ix >= 0x3ff00000;
    const double a = ge1 ? 2.0 * fabs(x) : -2.0 * fabs(x);
    const int64_t ha = (tf_bits(a) >> 32) & 0x7fffffff;
    int64_t k = 0;
    double r = a, c = 0.0;
    if (ha > 0x3fd62e42) {{
      double hi, lo;
      if (ha < 0x3ff0a2b2) {{
        k = a < 0 ? -1 : 1;
        hi = a < 0 ? a + {_LN2_HI} : a - {_LN2_HI};
        lo = a < 0 ? -{_LN2_LO} : {_LN2_LO};
      }} else {{
        k = (int64_t)({_INV_LN2} * a + (a < 0 ? -0.5 : 0.5));
        const double t = (double)k;
        hi = TF_FMA(-t, {_LN2_HI}, a);
        lo = t * {_LN2_LO};
      }}
      r = hi - lo;
      c = (hi - r) - lo;
    }}
    const double hfx = 0.5 * r, hxs = r * hfx, h2 = hxs * hxs, h4 = h2 * h2;
    const double r1 = TF_FMA(h4, TF_FMA(hxs, {_Q[4]}, {_Q[3]}),
                             TF_FMA(h2, TF_FMA(hxs, {_Q[2]}, {_Q[1]}), TF_FMA(hxs, {_Q[0]}, 1.0)));
    const double t3 = TF_FMA(-r1, hfx, 3.0);
    double e = hxs * ((r1 - t3) / TF_FMA(-r, t3, 6.0)), y;
    if (k == 0) y = r - TF_FMA(r, e, -hxs);
    else {{
      e = TF_FMA(e - c, r, -c) - hxs;
      if (k == -1) y = TF_FMA(0.5, r - e, -0.5);
      else if (k == 1) y = r < -0.25 ? -2.0 * (e - (r + 0.5)) : TF_FMA(r - e, 2.0, 1.0);
      else if (k <= -2 || k > 56) y = tf_double(tf_bits(1.0 - (e - r)) + (k << 52)) - 1.0;
      else if (k < 20)
        y = tf_double(tf_bits(tf_double((int64_t)(0x3ff00000 - (0x200000 >> k)) << 32) - (e - r))
                      + (k << 52));
      else y = tf_double(tf_bits((r - (e + tf_double((0x3ff - k) << 52))) + 1.0) + (k << 52));
    }}
    z = ge1 ? 1.0 - 2.0 / (y + 2.0) : -y / (y + 2.0);
  }}
  return b >= 0 ? z : -z;
}}
"""


def vector(w: int) -> str:
    """`v_tanh(vd)`: `SCALAR`'s tanh on `w` lanes, every branch evaluated and selected per lane
    (needs the SIMD prelude's `vd`, `vi`, `bd`, `bi`, `seld`, `seli`, `i2d`). Two of expm1's
    branches cannot occur inside tanh and are left out: its argument is 2|x| ≥ 2 or −2|x| > −2,
    so a positive one is reduced by k ≥ 3, never by the k = +1 of arguments below 1.5 ln 2."""
    return f"""\
static inline vd v_fma(vd a, vd b, vd c) {{
#if defined(__FMA__) && defined(__AVX2__)
  vd r; for (int l = 0; l < {w}; ++l) r[l] = fma(a[l], b[l], c[l]); return r;
#else
  return a * b + c;
#endif
}}
static inline vd v_tanh(vd x) {{
  const vi b = (vi)x, ix = (b >> 32) & bi(0x7fffffff), neg_x = (vi)(b < bi(0));
  const vi ge1 = (vi)(ix >= bi(0x3ff00000));
  const vd ax = (vd)(b & bi(0x7fffffffffffffffLL));
  const vd a = seld(ge1, bd(2.0) * ax, bd(-2.0) * ax);
  const vi ha = ((vi)a >> 32) & bi(0x7fffffff);
  const vi kg = __builtin_convertvector(bd({_INV_LN2}) * a + seld(ge1, bd(0.5), bd(-0.5)), vi);
  const vd tg = i2d(kg);
  const vi mid = (vi)(ha < bi(0x3ff0a2b2)), red = (vi)(ha > bi(0x3fd62e42));
  const vd hi = seld(mid, a + bd({_LN2_HI}), v_fma(-tg, bd({_LN2_HI}), a));
  const vd lo = seld(mid, bd(-{_LN2_LO}), tg * bd({_LN2_LO}));
  const vi k = seli(red, seli(mid, bi(-1), kg), bi(0));
  const vd rr = hi - lo, r = seld(red, rr, a), c = seld(red, (hi - rr) - lo, bd(0.0));
  const vd hfx = bd(0.5) * r, hxs = r * hfx, h2 = hxs * hxs, h4 = h2 * h2;
  const vd r1 = v_fma(h4, v_fma(hxs, bd({_Q[4]}), bd({_Q[3]})),
                      v_fma(h2, v_fma(hxs, bd({_Q[2]}), bd({_Q[1]})), v_fma(hxs, bd({_Q[0]}), bd(1.0))));
  const vd t3 = v_fma(-r1, hfx, bd(3.0));
  const vd e0 = hxs * ((r1 - t3) / v_fma(-r, t3, bd(6.0)));
  const vd e = v_fma(e0 - c, r, -c) - hxs;
  const vi kc = k & bi(63), scale = k << 52;
  const vd y_big = (vd)((vi)(bd(1.0) - (e - r)) + scale) - bd(1.0);
  const vd y_lt20 = (vd)((vi)((vd)((bi(0x3ff00000) - (bi(0x200000) >> (kc & bi(31)))) << 32)
                              - (e - r)) + scale);
  const vd y_ge20 = (vd)((vi)((r - (e + (vd)((bi(0x3ff) - kc) << 52))) + bd(1.0)) + scale);
  vd y = seld((vi)(k < bi(20)), y_lt20, y_ge20);
  y = seld((vi)(k <= bi(-2)) | (vi)(k > bi(56)), y_big, y);
  y = seld((vi)(k == bi(-1)), v_fma(bd(0.5), r - e, bd(-0.5)), y);
  y = seld((vi)(k == bi(0)), r - v_fma(r, e0, -hxs), y);
  const vd q = seld(ge1, bd(2.0), -y) / (y + bd(2.0));
  vd z = seld(ge1, bd(1.0) - q, q);
  z = seld((vi)(ix >= bi(0x40360000)), bd(1.0 - 1.0e-300), z);
  z = seld(neg_x, -z, z);
  z = seld((vi)(ix < bi(0x3c800000)), x * (bd(1.0) + x), z);
  return seld((vi)(x != x), x + x, z);
}}
"""
