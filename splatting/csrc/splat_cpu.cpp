// CPU kernels of pano-pipe's 360° Gaussian splatting renderer (see docs/splatting.md).
// Per-Gaussian packed parameters (PACK = 20 per row), built in splatting/project.py:
//   a1[3] a2[3] n[3] uc vc Q00 Q01 Q11 opacity rgb[3] dist tau
// A pixel with ray direction d: h = (a1·d, a2·d), c = n·d (> C_MIN),
// u = h0/c - uc, v = h1/c - vc, power = ½(Q00 u² + Q11 v²) + Q01 u v,
// skipped unless power <= tau; alpha = min(o·exp(-power), 0.99);
// front-to-back blending, a pixel stops once its transmittance falls below T_MIN.
#include <torch/extension.h>
#include <omp.h>
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <type_traits>
#include <vector>

#include "project_cpu.h"

namespace {

constexpr int PACK = 20;
constexpr double ALPHA_MAX = 0.99;
constexpr double T_MIN = 1e-4;
constexpr double C_MIN = 1e-6;
constexpr int MAX_TILE = 32;
// Tile entries read ahead by the rasteriser loops: an entry's rows of P are random
// accesses (most of P is outside the caches at 300k Gaussians) and one entry's work
// (a few rows of 8 lanes) is shorter than a memory access.
constexpr int PREFETCH = 4;

inline int nthreads() { return std::max(1, at::get_num_threads()); }
// Small jobs run on one thread: waking an OpenMP team costs more than they do
// (and far more on a loaded machine).
inline int threads_for(int64_t npairs, int ts) {
  return (npairs * ts * ts < 262144) ? 1 : nthreads();
}

// Tile lists: every Gaussian listed in `order` (front to back) is appended to each tile
// its pixel box touches. bbox rows: r0, r1 (inclusive), c0, ncols (columns wrap modulo W).

// x / ts for x >= 0, as a shift when ts is a power of two (the default tile sizes): a
// 64-bit division per box edge was most of the binning time.
struct TileDiv {
  int ts, shift;
  explicit TileDiv(int t) : ts(t), shift((t & (t - 1)) == 0 ? __builtin_ctz(t) : -1) {}
  int operator()(int x) const { return shift >= 0 ? x >> shift : x / ts; }
};

// Tiles of a pixel box: rows [tr0, tr1], and ntc tile columns from tc0 as one circular
// run (columns [c0, c0+n) wrap modulo W, and W need not be a multiple of ts, so the
// wrapped part restarts at tile 0).
struct TileBox {
  int tr0, tr1, tc0, ntc;
};
inline TileBox tile_box(const int32_t* b, int W, int ntx, const TileDiv& div) {
  const int c0 = b[2], end = b[2] + b[3], tc0 = div(c0);
  const int n = end > W ? ntx - tc0 + div(end - W - 1) + 1 : div(end - 1) - tc0 + 1;
  return {div(b[0]), div(b[1]), tc0, std::min(n, ntx)};
}

std::vector<torch::Tensor> bin_gaussians(torch::Tensor bbox, torch::Tensor order, int64_t H, int64_t W, int64_t ts) {
  TORCH_CHECK(bbox.dtype() == torch::kInt32 && bbox.is_contiguous(), "bbox must be contiguous int32");
  TORCH_CHECK(order.dtype() == torch::kInt64 && order.is_contiguous(), "order must be contiguous int64");
  const int ntx = (int)((W + ts - 1) / ts), nty = (int)((H + ts - 1) / ts);
  const int64_t ntiles = (int64_t)ntx * nty, nv = order.size(0), N = bbox.size(0);
  const int32_t* bb = bbox.data_ptr<int32_t>();
  const int64_t* ord = order.data_ptr<int64_t>();
  const TileDiv div((int)ts);
  // tile boxes of the listed Gaussians, in memory order (no rows for the others)
  std::vector<uint8_t> listed(N, 0);
  for (int64_t k = 0; k < nv; ++k) listed[ord[k]] = 1;
  std::vector<TileBox> tb(N);
  for (int64_t g = 0; g < N; ++g) tb[g] = listed[g] ? tile_box(bb + 4 * g, (int)W, ntx, div) : TileBox{0, -1, 0, 0};
  auto for_tiles = [&](const TileBox& t, auto&& f) {
    for (int64_t tr = t.tr0; tr <= t.tr1; ++tr) {
      const int64_t row = tr * ntx;
      for (int j = 0, c = t.tc0; j < t.ntc; ++j, c = (c + 1 == ntx ? 0 : c + 1)) f(row + c);
    }
  };
  auto toff = torch::zeros({ntiles + 1}, torch::kInt64);
  int64_t* off = toff.data_ptr<int64_t>();
  std::vector<int64_t> cnt(ntiles, 0);
  for (int64_t g = 0; g < N; ++g) for_tiles(tb[g], [&](int64_t t) { cnt[t]++; });  // counts need no order
  off[0] = 0;
  for (int64_t t = 0; t < ntiles; ++t) off[t + 1] = off[t] + cnt[t];
  auto tlist = torch::empty({off[ntiles]}, torch::kInt32);
  int32_t* tl = tlist.data_ptr<int32_t>();
  std::vector<int64_t> pos(off, off + ntiles);
  for (int64_t k = 0; k < nv; ++k) {
    if (k + 8 < nv) __builtin_prefetch(&tb[ord[k + 8]]);
    const int64_t g = ord[k];
    for_tiles(tb[g], [&](int64_t t) { tl[pos[t]++] = (int32_t)g; });
  }
  return {toff, tlist};
}

struct Span {
  int r0, r1;      // rows, inclusive, clipped to the tile
  int a0, a1;      // first column interval [a0, a1)
  int b0, b1;      // wrapped column interval [b0, b1)
};

inline bool tile_span(const int32_t* b, int y0, int y1, int x0, int x1, int W, Span& s) {
  s.r0 = std::max<int>(y0, b[0]);
  s.r1 = std::min<int>(y1 - 1, b[1]);
  if (s.r0 > s.r1) return false;
  const int c0 = b[2], cw = b[3];
  s.a0 = std::max(x0, c0);
  s.a1 = std::min(x1, c0 + cw);
  s.b0 = std::max(x0, c0 - W);
  s.b1 = std::min(x1, c0 + cw - W);
  return s.a0 < s.a1 || s.b0 < s.b1;
}

template <typename T>
struct G {
  T a1x, a1y, a1z, a2x, a2y, a2z, nx, ny, nz, uc, vc, q00, q01, q11, op, cr, cg, cb, dist, tau;
  explicit G(const T* p)
      : a1x(p[0]), a1y(p[1]), a1z(p[2]), a2x(p[3]), a2y(p[4]), a2z(p[5]), nx(p[6]), ny(p[7]), nz(p[8]),
        uc(p[9]), vc(p[10]), q00(p[11]), q01(p[12]), q11(p[13]), op(p[14]), cr(p[15]), cg(p[16]), cb(p[17]),
        dist(p[18]), tau(p[19]) {}
};

// exp_reduced(x, n) = exp(x) / 2^n with n = round(x / ln 2): the range reduction and polynomial,
// for a float or an 8-lane float vector (the same operations lane by lane).
template <typename F>
inline F exp_reduced(F x, F& n) {
  // n by the 1.5·2^23 trick (floorf is a libm call in scalar code)
  n = (x * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
  F r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  F y = F{} + 1.9875691500e-4f;
  y = y * r + 1.3981999507e-3f;
  y = y * r + 8.3334519073e-3f;
  y = y * r + 4.1665795894e-2f;
  y = y * r + 1.6666665459e-1f;
  y = y * r + 5.0000001201e-1f;
  return y * r * r + r + 1.0f;
}

// exp(x) for x <= 0 in float32 (Cephes expf: range reduction by ln 2 in two parts and a
// degree-6 polynomial, ~1 ulp; branch-free), cheaper than std::exp; float64 uses std::exp.
// Used for the hits only, identically in the forward and the backward.
inline float exp_neg_f32(float x) {
  x = std::max(x, -87.0f);
  float n;
  const float y = exp_reduced(x, n);
  const int32_t e = ((int32_t)n + 127) << 23;
  float sc;
  std::memcpy(&sc, &e, sizeof(sc));
  return y * sc;
}
template <typename T>
inline T gexp(T x) {
  if constexpr (std::is_same<T, float>::value) return exp_neg_f32(x);
  else return std::exp(x);
}

// The Gaussian at a pixel with ray direction d: c = n·d (ok: c > C_MIN; other pixels are
// not evaluated and get a finite dummy), (u, v) on the tangent plane, the power
// ½ (Q00 u² + Q11 v²) + Q01 u v, and ic = 1/c for the backward.
template <typename T>
struct Eval {
  T u, v, p, ic;
  bool ok;
};
template <typename T>
inline Eval<T> evaluate(const G<T>& q, T dx, T dy, T dz) {
  const T c = q.nx * dx + q.ny * dy + q.nz * dz;
  const bool ok = c > (T)C_MIN;
  const T ic = T(1) / (ok ? c : T(1));
  const T u = (q.a1x * dx + q.a1y * dy + q.a1z * dz) * ic - q.uc;
  const T v = (q.a2x * dx + q.a2y * dy + q.a2z * dz) * ic - q.vc;
  return {u, v, T(0.5) * (q.q00 * u * u + q.q11 * v * v) + q.q01 * u * v, ic, ok};
}

// Columns of a tile row that a Gaussian's pixel box covers: lanes [a0, a1) and the
// wrapped part [b0, b1), relative to the tile's first column.
struct Lanes {
  int a0, a1, b0, b1;
  bool has(int j) const { return ((j >= a0) & (j < a1)) | ((j >= b0) & (j < b1)); }  // no branches
};

// The lanes of a tile row that one box needs: an 8-lane window where the box's columns
// fit in 8 (on a 16-wide tile that halves the work of most small splats), else the row.
// nl is 16 or 8 (compile-time widths) or 0 (any other tile width: all tw lanes).
struct Window {
  int h, nl;  // first lane, width
  Lanes ln;   // relative to h
};
inline Window lane_window(const Lanes& ln, int tw) {
  int lo = MAX_TILE, hi = 0;
  if (ln.a0 < ln.a1) lo = std::min(lo, ln.a0), hi = std::max(hi, ln.a1);
  if (ln.b0 < ln.b1) lo = std::min(lo, ln.b0), hi = std::max(hi, ln.b1);
  if (tw == 16 && hi - lo <= 8) {
    const int h = std::min(lo, 8);
    return {h, 8, {ln.a0 - h, ln.a1 - h, ln.b0 - h, ln.b1 - h}};
  }
  return {0, (tw == 16 || tw == 8) ? tw : 0, ln};
}

// Calls row(width, dx, dy, dz, i, lanes) for each row of a span inside its tile: width is
// the lane window's compile-time width (std::integral_constant 16, 8, or 0 = generic),
// dx/dy/dz the window's ray directions and i its first pixel in the tile buffers.
template <typename T, typename F>
inline void for_span_rows(const Span& s, const T* dirs, int64_t HW, int W, int x0, int y0, int tw, F&& row) {
  const Window wd = lane_window({s.a0 - x0, s.a1 - x0, s.b0 - x0, s.b1 - x0}, tw);
  for (int r = s.r0; r <= s.r1; ++r) {
    const int64_t o = (int64_t)r * W + x0 + wd.h;
    const int i = (r - y0) * tw + wd.h;
    const T *dx = dirs + o, *dy = dirs + HW + o, *dz = dirs + 2 * HW + o;
    if (wd.nl == 16) row(std::integral_constant<int, 16>(), dx, dy, dz, i, wd.ln);
    else if (wd.nl == 8) row(std::integral_constant<int, 8>(), dx, dy, dz, i, wd.ln);
    else row(std::integral_constant<int, 0>(), dx, dy, dz, i, wd.ln);
  }
}

// One tile row of the forward, all lanes at once so that the compiler vectorises it:
// NL lanes (a compile-time tile width, one or two vector registers, no scalar
// remainder), or n lanes if NL == 0. A lane outside the box, missed by the Gaussian
// (power > tau, c <= C_MIN, or a NaN) or already saturated gets alpha = 0 through a
// select, which leaves its sums bit-identical. Directions are stored as three planes.
// Returns the number of pixels blended; adds the pixels that saturated to `nsat`.
template <typename T, int NL>
inline int row_forward(const G<T>& q, const T* __restrict dx, const T* __restrict dy, const T* __restrict dz, int n,
                       Lanes ln, int32_t k, T* __restrict Tr, T* __restrict aR, T* __restrict aG,
                       T* __restrict aB, T* __restrict dep, int32_t* __restrict last, int& nsat) {
  int nblend = 0, ndone = 0;
  const int m = NL ? NL : n;
#pragma omp simd reduction(+ : nblend, ndone)
  for (int j = 0; j < m; ++j) {
    const Eval<T> ev = evaluate(q, dx[j], dy[j], dz[j]);
    const T p = ev.p;
    const T t = Tr[j];
    const bool h = ln.has(j) & ev.ok & (p <= q.tau) & (t >= (T)T_MIN);
    const T e = gexp<T>(h ? -p : T(0));
    const T alpha = h ? std::min(q.op * e, (T)ALPHA_MAX) : T(0);
    const T w = alpha * t;
    aR[j] += w * q.cr;
    aG[j] += w * q.cg;
    aB[j] += w * q.cb;
    dep[j] += w * q.dist;
    const T tn = t * (T(1) - alpha);
    Tr[j] = tn;
    last[j] = h ? k : last[j];
    nblend += h;
    ndone += h & (tn < (T)T_MIN);
  }
  nsat += ndone;
  return nblend;
}

// Per-(Gaussian, tile) gradient sums with respect to the packed parameters (PACK order).
template <typename T>
struct PackGrad {
  T v[PACK - 1] = {};
};

// One tile row of the backward, vectorised like row_forward: pixels behind the
// Gaussian's last blend (k > last) or missed by it contribute nothing through selects.
// Returns the number of pixels that had blended this Gaussian.
template <typename T, int NL>
inline int row_backward(const G<T>& q, const T* __restrict dx, const T* __restrict dy, const T* __restrict dz, int n,
                        Lanes ln, int32_t k, const int32_t* __restrict last, T* __restrict Tr, T* __restrict Sg,
                        const T* __restrict gCr, const T* __restrict gCg, const T* __restrict gCb,
                        const T* __restrict gD, const T* __restrict gA, PackGrad<T>& acc) {
  T ga1x = 0, ga1y = 0, ga1z = 0, ga2x = 0, ga2y = 0, ga2z = 0, gnx = 0, gny = 0, gnz = 0, guc = 0, gvc = 0,
    gq00 = 0, gq01 = 0, gq11 = 0, gop = 0, gcr = 0, gcg = 0, gcb = 0, gdist = 0;
  int nact = 0;
  const int m = NL ? NL : n;
#pragma omp simd reduction(+ : ga1x, ga1y, ga1z, ga2x, ga2y, ga2z, gnx, gny, gnz, guc, gvc, gq00, gq01, gq11, gop, \
                               gcr, gcg, gcb, gdist, nact)
  for (int j = 0; j < m; ++j) {
    const Eval<T> ev = evaluate(q, dx[j], dy[j], dz[j]);
    const T u = ev.u, v = ev.v, p = ev.p, ic = ev.ic;
    const bool h = ln.has(j) & ev.ok & (p <= q.tau) & (k <= last[j]);
    const T Gv = gexp<T>(h ? -p : T(0));
    const T oG = q.op * Gv;
    const T alpha = h ? std::min(oG, (T)ALPHA_MAX) : T(0);
    const T ioma = T(1) / (T(1) - alpha);
    const T Ti = Tr[j] * ioma;
    const T w = alpha * Ti;
    const T xg = q.cr * gCr[j] + q.cg * gCg[j] + q.cb * gCb[j] + q.dist * gD[j] + gA[j];
    const T dLda = Ti * xg - Sg[j] * ioma;
    Sg[j] = h ? Sg[j] + w * xg : Sg[j];
    Tr[j] = h ? Ti : Tr[j];
    nact += h;
    gcr += h ? w * gCr[j] : T(0);
    gcg += h ? w * gCg[j] : T(0);
    gcb += h ? w * gCb[j] : T(0);
    gdist += h ? w * gD[j] : T(0);
    // no gradient through the 0.99 clamp (docs/splatting.md)
    const bool g = h & (oG < (T)ALPHA_MAX);
    const T dpow = -oG * dLda;
    const T du = dpow * (q.q00 * u + q.q01 * v);
    const T dv = dpow * (q.q01 * u + q.q11 * v);
    gop += g ? Gv * dLda : T(0);
    gq00 += g ? T(0.5) * dpow * u * u : T(0);
    gq01 += g ? dpow * u * v : T(0);
    gq11 += g ? T(0.5) * dpow * v * v : T(0);
    guc -= g ? du : T(0);
    gvc -= g ? dv : T(0);
    // h0 = (u + uc) c, h1 = (v + vc) c
    const T dh0 = g ? du * ic : T(0), dh1 = g ? dv * ic : T(0);
    const T dc = -(dh0 * (u + q.uc) + dh1 * (v + q.vc));
    ga1x += dh0 * dx[j]; ga1y += dh0 * dy[j]; ga1z += dh0 * dz[j];
    ga2x += dh1 * dx[j]; ga2y += dh1 * dy[j]; ga2z += dh1 * dz[j];
    gnx += g ? dc * dx[j] : T(0); gny += g ? dc * dy[j] : T(0); gnz += g ? dc * dz[j] : T(0);
  }
  const T sums[PACK - 1] = {ga1x, ga1y, ga1z, ga2x, ga2y, ga2z, gnx, gny, gnz, guc, gvc,
                            gq00, gq01, gq11, gop, gcr, gcg, gcb, gdist};
  for (int i = 0; i < PACK - 1; ++i) acc.v[i] += sums[i];
  return nact;
}

// r[i] = Σ_j v_i[j] for eight 8-lane vectors: three levels of shuffles and adds, the lanes of
// each level ordered so that the sums come out in input order.
template <typename V, typename M>
inline V lane_sums8(V v0, V v1, V v2, V v3, V v4, V v5, V v6, V v7) {
  const M h1a = {0, 1, 2, 3, 8, 9, 10, 11}, h1b = {4, 5, 6, 7, 12, 13, 14, 15};
  const M h2a = {0, 1, 8, 9, 4, 5, 12, 13}, h2b = {2, 3, 10, 11, 6, 7, 14, 15};
  const M h3a = {0, 2, 4, 6, 8, 10, 12, 14}, h3b = {1, 3, 5, 7, 9, 11, 13, 15};
  auto l1 = [&](V a, V b) { return __builtin_shuffle(a, b, h1a) + __builtin_shuffle(a, b, h1b); };
  auto l2 = [&](V a, V b) { return __builtin_shuffle(a, b, h2a) + __builtin_shuffle(a, b, h2b); };
  auto l3 = [&](V a, V b) { return __builtin_shuffle(a, b, h3a) + __builtin_shuffle(a, b, h3b); };
  return l3(l2(l1(v0, v2), l1(v1, v3)), l2(l1(v4, v6), l1(v5, v7)));
}

// The backward's vector: R rows of an 8-column window in one register. With AVX-512 a float
// vector holds two rows (16 lanes), which halves the instructions of a span's rows (a span
// has ~10 rows on average); otherwise, and for double, one row. Rows are loaded and stored
// as 8-lane halves at `p` and `p + step`; step = 0 repeats the first row (a span's odd last
// row), whose upper half is then masked out and not stored.
template <typename T>
struct Rows {
#if defined(__AVX512F__)
  static constexpr int R = sizeof(T) == 4 ? 2 : 1;
#else
  static constexpr int R = 1;
#endif
  static constexpr int L = 8 * R;
  typedef T V __attribute__((vector_size(L * sizeof(T))));
  typedef typename std::conditional<sizeof(T) == 4, int32_t, int64_t>::type I;
  typedef I M __attribute__((vector_size(L * sizeof(T))));
  typedef T V8 __attribute__((vector_size(8 * sizeof(T))));
  typedef I M8 __attribute__((vector_size(8 * sizeof(T))));
  typedef int32_t I8 __attribute__((vector_size(32)));

#if defined(__AVX512F__)
  static V load(const T* p, int64_t step) {
    if constexpr (R == 2) {
      const __m512 lo = _mm512_castps256_ps512(_mm256_loadu_ps(p));
      return (V)_mm512_castpd_ps(
          _mm512_insertf64x4(_mm512_castps_pd(lo), _mm256_castps_pd(_mm256_loadu_ps(p + step)), 1));
    } else {
      return load1(p);
    }
  }
  static void store(T* p, int64_t step, V v, bool two) {
    if constexpr (R == 2) {
      _mm256_storeu_ps(p, _mm512_castps512_ps256((__m512)v));
      if (two) _mm256_storeu_ps(p + step, _mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd((__m512)v), 1)));
    } else {
      std::memcpy(p, &v, sizeof(V));
    }
  }
  static M load_last(const int32_t* p, int64_t step) {
    if constexpr (R == 2) {
      const __m512i lo = _mm512_castsi256_si512(_mm256_loadu_si256((const __m256i*)p));
      return (M)_mm512_inserti64x4(lo, _mm256_loadu_si256((const __m256i*)(p + step)), 1);
    } else {
      return load_last1(p);
    }
  }
  static void store_last(int32_t* p, int64_t step, M v, bool two) {
    if constexpr (R == 2) {
      _mm256_storeu_si256((__m256i*)p, _mm512_castsi512_si256((__m512i)v));
      if (two) _mm256_storeu_si256((__m256i*)(p + step), _mm512_extracti64x4_epi64((__m512i)v, 1));
    } else {
      store_last1(p, v);
    }
  }
#else
  static void store_last(int32_t* p, int64_t, M v, bool) { store_last1(p, v); }
  static V load(const T* p, int64_t) { return load1(p); }
  static void store(T* p, int64_t, V v, bool) { std::memcpy(p, &v, sizeof(V)); }
  static M load_last(const int32_t* p, int64_t) { return load_last1(p); }
#endif
  static V load1(const T* p) {
    V v;
    std::memcpy(&v, p, sizeof(V));
    return v;
  }
  static void store_last1(int32_t* p, M v) {
    if constexpr (sizeof(T) == 4) {
      std::memcpy(p, &v, sizeof(I8));
    } else {
      const I8 w = __builtin_convertvector(v, I8);
      std::memcpy(p, &w, sizeof(I8));
    }
  }
  static M load_last1(const int32_t* p) {
    I8 v;
    std::memcpy(&v, p, sizeof(I8));
    if constexpr (sizeof(T) == 4) return (M)v;
    else return __builtin_convertvector(v, M);
  }
  // the sum of the R rows' lanes, as one 8-lane vector
  static V8 fold(V v) {
    if constexpr (R == 2) {
      V8 a, b;
      std::memcpy(&a, &v, sizeof(V8));
      std::memcpy(&b, reinterpret_cast<const char*>(&v) + sizeof(V8), sizeof(V8));
      return a + b;
    } else {
      return (V8)v;
    }
  }
};

// exp(x) for x <= 0 lane by lane, the same operations as exp_neg_f32 (float) or std::exp.
template <typename V, typename M>
inline V vexp_neg(V x) {
  if constexpr (std::is_same<decltype(x[0] + 0), float>::value) {
    x = x > -87.0f ? x : V{} - 87.0f;
    V n;
    const V y = exp_reduced(x, n);
    const M e = (__builtin_convertvector(n, M) + 127) << 23;
    return y * (V)e;
  } else {
    for (int j = 0; j < (int)(sizeof(V) / sizeof(x[0])); ++j) x[j] = std::exp(x[j]);
    return x;
  }
}

// Walks a (Gaussian, tile) span in Rows vectors: 8-column windows from the span's first
// column (the last one moved left to end at the tile's edge, its lanes before `from`
// belonging to the previous window), R rows per vector, and evaluates the Gaussian there.
// Calls body(i, si, two, live, u, v, p): i the first pixel in the tile buffers, si the step to
// the second row (0 if none; `two` says whether there is one), live the lanes inside the box
// and in front of the tangent plane, (u, v) and p the offset and power (as `evaluate`). The
// forward and the backward share it, so the backward recomputes every alpha bit for bit.
template <typename T, typename F>
__attribute__((always_inline)) inline void for_span_vectors(const G<T>& q, const Span& s, const T* dirs, int64_t HW, int W, int x0, int y0, int tw,
                             F&& body) {
  using X = Rows<T>;
  using V = typename X::V;
  using M = typename X::M;
  constexpr int R = X::R;
  // the span's columns relative to the tile: [a0, a1) and the wrapped [b0, b1)
  const int a0 = s.a0 - x0, a1 = s.a1 - x0, b0 = s.b0 - x0, b1 = s.b1 - x0;
  int lo = tw, hi = 0;
  if (a0 < a1) lo = std::min(lo, a0), hi = std::max(hi, a1);
  if (b0 < b1) lo = std::min(lo, b0), hi = std::max(hi, b1);
  M col8, upper;  // lane -> column in its 8-lane row; lanes of the second row
  for (int j = 0; j < X::L; ++j) col8[j] = j % 8, upper[j] = j >= 8 ? -1 : 0;
  const V one = V{} + T(1);
  for (int from = lo; from < hi; from += 8) {
    const int h = std::min(from, tw - 8);
    const M col = col8 + h;
    const M lanes = (((col >= a0) & (col < a1)) | ((col >= b0) & (col < b1))) & (col >= from);
    for (int r = s.r0; r <= s.r1; r += R) {
      const bool two = R == 2 && r < s.r1;
      const int64_t o = (int64_t)r * W + x0 + h, so = two ? W : 0;
      const int i = (r - y0) * tw + h, si = two ? tw : 0;
      const V dx = X::load(dirs + o, so), dy = X::load(dirs + HW + o, so), dz = X::load(dirs + 2 * HW + o, so);
      const V c = q.nx * dx + q.ny * dy + q.nz * dz;
      const M ok = c > (T)C_MIN;
      const V ic = one / (ok ? c : one);
      const V u = (q.a1x * dx + q.a1y * dy + q.a1z * dz) * ic - q.uc;
      const V v = (q.a2x * dx + q.a2y * dy + q.a2z * dz) * ic - q.vc;
      const V p = T(0.5) * (q.q00 * u * u + q.q11 * v * v) + q.q01 * u * v;
      body(i, si, two, (two ? lanes : lanes & ~upper) & ok, u, v, p);
    }
  }
}

// The backward of one (Gaussian, tile) span in explicit vectors (GCC/Clang vector
// extensions, Rows above): the gradient sums stay per lane in registers over all the rows of
// the span and are summed over the lanes once at its end (row_backward's per-row horizontal
// sums, the compiler's reduction of `omp simd`, were most of its time).
//
// The 9 sums of the ray-direction gradients (a1, a2, n: Σ ∂L/∂h0 · d, ...) are not summed
// per lane: a1, a2 and n are orthogonal (s·e1, s·e2, n for the panorama; sx·x̂, sy·ŷ, ẑ for
// the pinhole), so every ray is d = c n + h0 a1/|a1|² + h1 a2/|a2|² with h0 = U c, h1 = V c
// (U = u + uc, V = v + vc), and each of those sums is a combination of the sums of du, dv,
// dpow·(u², uv, v²) (which the conic and centre gradients need anyway) and two more, K·U
// and K·V with K = du U + dv V. Twelve sums instead of nineteen fit the registers.
// DA: whether the depth and alpha images have a gradient (training passes none; their terms
// are 7 % of this loop).
template <typename T, bool DA>
inline bool span_backward(const G<T>& q, const Span& s, const T* dirs, int64_t HW, int W, int x0, int y0, int tw,
                          int32_t k, const int32_t* __restrict last, T* __restrict Tr, T* __restrict Sg,
                          const T* __restrict gCr, const T* __restrict gCg, const T* __restrict gCb,
                          const T* __restrict gD, const T* __restrict gA, PackGrad<T>& acc) {
  using X = Rows<T>;
  using V = typename X::V;
  using M = typename X::M;
  const V zero = V{}, one = zero + T(1);
  V sdu = zero, sdv = zero, suu = zero, suv = zero, svv = zero, sku = zero, skv = zero, sop = zero, scr = zero,
    scg = zero, scb = zero, sdist = zero;
  M anyv = M{};
  for_span_vectors<T>(q, s, dirs, HW, W, x0, y0, tw, [&](int i, int si, bool two, M live, V u, V v, V p) __attribute__((always_inline)) {
    const M h_ = live & (p <= q.tau) & (k <= X::load_last(last + i, si));
    const V Gv = vexp_neg<V, M>(h_ ? -p : zero);
    const V oG = q.op * Gv;
    const V alpha = h_ ? (oG < (T)ALPHA_MAX ? oG : zero + (T)ALPHA_MAX) : zero;
    const V ioma = one / (one - alpha);
    const V tr = X::load(Tr + i, si), sg = X::load(Sg + i, si);
    const V Ti = tr * ioma;
    const V w = alpha * Ti;
    const V gr = X::load(gCr + i, si), gg = X::load(gCg + i, si), gb = X::load(gCb + i, si);
    V xg = q.cr * gr + q.cg * gg + q.cb * gb;
    if constexpr (DA) {
      const V gd = X::load(gD + i, si);
      xg += q.dist * gd + X::load(gA + i, si);
      sdist += h_ ? w * gd : zero;
    }
    const V dLda = Ti * xg - sg * ioma;
    X::store(Sg + i, si, h_ ? sg + w * xg : sg, two);
    X::store(Tr + i, si, h_ ? Ti : tr, two);
    anyv |= h_;
    scr += h_ ? w * gr : zero;
    scg += h_ ? w * gg : zero;
    scb += h_ ? w * gb : zero;
    // no gradient through the 0.99 clamp (docs/splatting.md)
    const M g = h_ & (oG < (T)ALPHA_MAX);
    const V dpow = g ? -oG * dLda : zero;  // zero off the hits: every sum below vanishes there
    sop += g ? Gv * dLda : zero;
    const V du = dpow * (q.q00 * u + q.q01 * v);
    const V dv = dpow * (q.q01 * u + q.q11 * v);
    const V pu = dpow * u;
    suu += pu * u;
    suv += pu * v;
    svv += dpow * v * v;
    sdu += du;
    sdv += dv;
    const V U = u + q.uc, Vv = v + q.vc;
    const V K = du * U + dv * Vv;
    sku += K * U;
    skv += K * Vv;
  });
  bool any = false;
  for (int j = 0; j < X::L; ++j) any |= anyv[j] != 0;
  if (!any) return false;
  using V8 = typename X::V8;
  using M8 = typename X::M8;
  const V8 z8 = V8{};
  const V8 r0 = lane_sums8<V8, M8>(X::fold(sdu), X::fold(sdv), X::fold(suu), X::fold(suv), X::fold(svv),
                                   X::fold(sku), X::fold(skv), X::fold(sop));
  const V8 r1 = lane_sums8<V8, M8>(X::fold(scr), X::fold(scg), X::fold(scb), X::fold(sdist), z8, z8, z8, z8);
  const T Sdu = r0[0], Sdv = r0[1], Suu = r0[2], Suv = r0[3], Svv = r0[4], SKU = r0[5], SKV = r0[6];
  // Σ du·U, Σ du·V, Σ dv·U, Σ dv·V from the conic sums
  const T duU = q.q00 * Suu + q.q01 * Suv + q.uc * Sdu, duV = q.q00 * Suv + q.q01 * Svv + q.vc * Sdu;
  const T dvU = q.q01 * Suu + q.q11 * Suv + q.uc * Sdv, dvV = q.q01 * Suv + q.q11 * Svv + q.vc * Sdv;
  const T SK = duU + dvV;
  const T i1 = T(1) / (q.a1x * q.a1x + q.a1y * q.a1y + q.a1z * q.a1z);
  const T i2 = T(1) / (q.a2x * q.a2x + q.a2y * q.a2y + q.a2z * q.a2z);
  const T n[3] = {q.nx, q.ny, q.nz}, e1[3] = {q.a1x * i1, q.a1y * i1, q.a1z * i1},
          e2[3] = {q.a2x * i2, q.a2y * i2, q.a2z * i2};
  for (int j = 0; j < 3; ++j) {
    acc.v[j] += n[j] * Sdu + e1[j] * duU + e2[j] * duV;       // ∂/∂a1 = Σ du ic d
    acc.v[3 + j] += n[j] * Sdv + e1[j] * dvU + e2[j] * dvV;   // ∂/∂a2 = Σ dv ic d
    acc.v[6 + j] -= n[j] * SK + e1[j] * SKU + e2[j] * SKV;    // ∂/∂n = -Σ K ic d
  }
  acc.v[9] -= Sdu;
  acc.v[10] -= Sdv;
  acc.v[11] += T(0.5) * Suu;
  acc.v[12] += Suv;
  acc.v[13] += T(0.5) * Svv;
  acc.v[14] += r0[7];
  for (int j = 0; j < 4; ++j) acc.v[15 + j] += r1[j];
  return true;
}

// The forward of one (Gaussian, tile) span in the backward's vectors (Rows: two rows per
// register with AVX-512), with the same per-lane operations as row_forward and the
// evaluation of span_backward (for_span_vectors). Returns whether any pixel blended; adds
// the pixels that saturated to `nsat`.
template <typename T>
inline bool span_forward(const G<T>& q, const Span& s, const T* dirs, int64_t HW, int W, int x0, int y0, int tw,
                         int32_t k, T* __restrict Tr, T* __restrict aR, T* __restrict aG, T* __restrict aB,
                         T* __restrict dep, int32_t* __restrict last, int& nsat) {
  using X = Rows<T>;
  using V = typename X::V;
  using M = typename X::M;
  const V zero = V{}, one = zero + T(1);
  const M kv = M{} + k;
  M anyv = M{}, satv = M{};
  for_span_vectors<T>(q, s, dirs, HW, W, x0, y0, tw, [&](int i, int si, bool two, M live, V, V, V p) __attribute__((always_inline)) {
    const V t = X::load(Tr + i, si);
    const M h_ = live & (p <= q.tau) & (t >= (T)T_MIN);
    const V Gv = vexp_neg<V, M>(h_ ? -p : zero);
    const V oG = q.op * Gv;
    const V alpha = h_ ? (oG < (T)ALPHA_MAX ? oG : zero + (T)ALPHA_MAX) : zero;
    const V w = alpha * t;
    X::store(aR + i, si, X::load(aR + i, si) + w * q.cr, two);
    X::store(aG + i, si, X::load(aG + i, si) + w * q.cg, two);
    X::store(aB + i, si, X::load(aB + i, si) + w * q.cb, two);
    X::store(dep + i, si, X::load(dep + i, si) + w * q.dist, two);
    const V tn = t * (one - alpha);
    X::store(Tr + i, si, tn, two);
    X::store_last(last + i, si, h_ ? kv : X::load_last(last + i, si), two);
    anyv |= h_;
    satv -= h_ & (tn < (T)T_MIN);  // lanes are 0 or -1
  });
  bool any = false;
  for (int j = 0; j < X::L; ++j) any |= anyv[j] != 0, nsat += (int)satv[j];
  return any;
}

template <typename T>
void forward_impl(const T* dirs, const T* P, const int32_t* bbox, const int64_t* toff, const int32_t* tlist, int H,
                  int W, int ts, T* out_color, T* out_depth, T* out_T, int32_t* out_last, uint8_t* hit) {
  const int ntx = (W + ts - 1) / ts, nty = (H + ts - 1) / ts, ntiles = ntx * nty;
  const int nt = threads_for(toff[ntiles], ts);
  const int64_t HW = (int64_t)H * W;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
  for (int tile = 0; tile < ntiles; ++tile) {
    const int ty = tile / ntx, tx = tile % ntx;
    const int y0 = ty * ts, y1 = std::min(H, y0 + ts), x0 = tx * ts, x1 = std::min(W, x0 + ts);
    const int tw = x1 - x0, npx = tw * (y1 - y0);
    T Tr[MAX_TILE * MAX_TILE], accR[MAX_TILE * MAX_TILE], accG[MAX_TILE * MAX_TILE], accB[MAX_TILE * MAX_TILE],
        dep[MAX_TILE * MAX_TILE];
    int32_t last[MAX_TILE * MAX_TILE];
    for (int i = 0; i < npx; ++i) {
      Tr[i] = 1;
      accR[i] = accG[i] = accB[i] = 0;
      dep[i] = 0;
      last[i] = -1;
    }
    int ndone = 0;
    for (int64_t k = toff[tile]; k < toff[tile + 1] && ndone < npx; ++k) {
      const int g = tlist[k];
      if (k + PREFETCH < toff[tile + 1]) {  // later entries' rows are random accesses: fetch them early
        const int gn = tlist[k + PREFETCH];
        __builtin_prefetch(P + (int64_t)gn * PACK);
        __builtin_prefetch(P + (int64_t)gn * PACK + PACK - 1);
        __builtin_prefetch(bbox + 4 * gn);
      }
      Span s;
      if (!tile_span(bbox + 4 * g, y0, y1, x0, x1, W, s)) continue;
      const G<T> q(P + (int64_t)g * PACK);
      int any = 0;
      if (tw >= 8) {
        any = span_forward<T>(q, s, dirs, HW, W, x0, y0, tw, (int32_t)k, Tr, accR, accG, accB, dep, last, ndone);
      } else {  // tiles narrower than a vector: one row at a time
        for_span_rows<T>(s, dirs, HW, W, x0, y0, tw, [&](auto nl, const T* dx, const T* dy, const T* dz, int i, Lanes ln) {
          any |= row_forward<T, decltype(nl)::value>(q, dx, dy, dz, tw, ln, (int32_t)k, Tr + i, accR + i, accG + i,
                                                     accB + i, dep + i, last + i, ndone) > 0;
        });
      }
      hit[k] = any;  // the backward skips entries that blended nothing in this tile
    }
    for (int r = y0; r < y1; ++r)
      for (int col = x0; col < x1; ++col) {
        const int i = (r - y0) * tw + (col - x0);
        const int64_t o = (int64_t)r * W + col;
        out_color[3 * o] = accR[i];
        out_color[3 * o + 1] = accG[i];
        out_color[3 * o + 2] = accB[i];
        out_depth[o] = dep[i];
        out_T[o] = Tr[i];
        out_last[o] = last[i];
      }
  }
}

template <typename T, bool DA>
void backward_impl(const T* dirs, const T* P, const int32_t* bbox, const int64_t* toff, const int32_t* tlist, int H,
                   int W, int ts, const T* gcol, const T* gdep, const T* galpha, const T* Tfin, const int32_t* lastk,
                   const uint8_t* hit, int nt, T* pgrad /* [pairs, PACK - 1] */, uint8_t* written) {
  const int ntx = (W + ts - 1) / ts, nty = (H + ts - 1) / ts, ntiles = ntx * nty;
  const int64_t HW = (int64_t)H * W;
#pragma omp parallel num_threads(nt)
  {
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < ntiles; ++tile) {
      const int ty = tile / ntx, tx = tile % ntx;
      const int y0 = ty * ts, y1 = std::min(H, y0 + ts), x0 = tx * ts, x1 = std::min(W, x0 + ts);
      const int tw = x1 - x0;
      T Tr[MAX_TILE * MAX_TILE], Sg[MAX_TILE * MAX_TILE], gCr[MAX_TILE * MAX_TILE], gCg[MAX_TILE * MAX_TILE],
          gCb[MAX_TILE * MAX_TILE], gD[MAX_TILE * MAX_TILE], gA[MAX_TILE * MAX_TILE];
      int32_t last[MAX_TILE * MAX_TILE];
      int64_t kmax = -1;
      for (int r = y0; r < y1; ++r)
        for (int col = x0; col < x1; ++col) {
          const int i = (r - y0) * tw + (col - x0);
          const int64_t o = (int64_t)r * W + col;
          Tr[i] = Tfin[o];
          Sg[i] = 0;
          gCr[i] = gcol[3 * o];
          gCg[i] = gcol[3 * o + 1];
          gCb[i] = gcol[3 * o + 2];
          gD[i] = gdep[o];
          gA[i] = galpha[o];
          last[i] = lastk[o];
          kmax = std::max<int64_t>(kmax, lastk[o]);
        }
      for (int64_t k = kmax; k >= toff[tile]; --k) {
        if (k - PREFETCH >= toff[tile]) {  // prefetch a later entry's parameters (random accesses)
          const int gp = tlist[k - PREFETCH];
          __builtin_prefetch(P + (int64_t)gp * PACK);
          __builtin_prefetch(P + (int64_t)gp * PACK + PACK - 1);
          __builtin_prefetch(bbox + 4 * gp);
        }
        if (!hit[k]) continue;
        const int g = tlist[k];
        Span s;
        if (!tile_span(bbox + 4 * g, y0, y1, x0, x1, W, s)) continue;
        const G<T> q(P + (int64_t)g * PACK);
        // per-(Gaussian, tile) sums in the working precision (at most ts² terms), stored
        // at the entry's index; reduce_pairs adds each Gaussian's entries in double
        PackGrad<T> acc;
        int any = 0;
        if (tw >= 8) {
          any = span_backward<T, DA>(q, s, dirs, HW, W, x0, y0, tw, (int32_t)k, last, Tr, Sg, gCr, gCg, gCb, gD, gA, acc);
        } else {  // tiles narrower than a vector: one row at a time
          for_span_rows<T>(s, dirs, HW, W, x0, y0, tw, [&](auto nl, const T* dx, const T* dy, const T* dz, int i, Lanes ln) {
            any |= row_backward<T, decltype(nl)::value>(q, dx, dy, dz, tw, ln, (int32_t)k, last + i, Tr + i, Sg + i,
                                                        gCr + i, gCg + i, gCb + i, gD + i, gA + i, acc) > 0;
          });
        }
        if (any) {
          std::memcpy(pgrad + k * (PACK - 1), acc.v, sizeof(acc.v));
          written[k] = 1;
        }
      }
    }
  }
}

// gP[g] = Σ of the per-entry sums of Gaussian g's tile entries (in double). The entries of
// each Gaussian are gathered by a counting sort of the tile lists: no [threads, N] buffer to
// zero and add up (at 300k Gaussians those were ~100 MB of memory traffic per backward).
template <typename T>
void reduce_pairs(const T* pgrad, const uint8_t* written, const int32_t* tlist, int64_t npairs, int64_t nv, int nt,
                  T* gP) {
  std::vector<int64_t> start(nv + 1, 0), entry;
  for (int64_t k = 0; k < npairs; ++k) start[tlist[k] + 1] += written[k];
  for (int64_t g = 0; g < nv; ++g) start[g + 1] += start[g];
  entry.resize(start[nv]);
  {
    std::vector<int64_t> pos(start.begin(), start.end() - 1);
    for (int64_t k = 0; k < npairs; ++k)
      if (written[k]) entry[pos[tlist[k]]++] = k;
  }
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int64_t g = 0; g < nv; ++g) {
    double acc[PACK] = {};
    for (int64_t e = start[g]; e < start[g + 1]; ++e) {
      const T* row = pgrad + entry[e] * (PACK - 1);
      for (int i = 0; i < PACK - 1; ++i) acc[i] += row[i];
    }
    for (int i = 0; i < PACK; ++i) gP[g * PACK + i] = (T)acc[i];
  }
}

std::vector<torch::Tensor> forward(torch::Tensor P, torch::Tensor dirs, torch::Tensor bbox, torch::Tensor toff,
                                   torch::Tensor tlist, int64_t H, int64_t W, int64_t ts) {
  TORCH_CHECK(ts >= 1 && ts <= MAX_TILE, "tile size must be 1..32");
  TORCH_CHECK(P.is_contiguous() && dirs.is_contiguous() && P.dtype() == dirs.dtype(), "bad inputs");
  TORCH_CHECK(dirs.dim() == 3 && dirs.size(0) == 3 && dirs.size(1) == H && dirs.size(2) == W, "dirs must be [3,H,W]");
  auto opts = P.options();
  auto color = torch::empty({H, W, 3}, opts);
  auto depth = torch::empty({H, W}, opts);
  auto Tf = torch::empty({H, W}, opts);
  auto last = torch::empty({H, W}, torch::kInt32);
  auto hit = torch::zeros({tlist.size(0)}, torch::kUInt8);
  AT_DISPATCH_FLOATING_TYPES(P.scalar_type(), "splat_forward", [&] {
    forward_impl<scalar_t>(dirs.data_ptr<scalar_t>(), P.data_ptr<scalar_t>(), bbox.data_ptr<int32_t>(),
                           toff.data_ptr<int64_t>(), tlist.data_ptr<int32_t>(), (int)H, (int)W, (int)ts,
                           color.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(), Tf.data_ptr<scalar_t>(),
                           last.data_ptr<int32_t>(), hit.data_ptr<uint8_t>());
  });
  return {color, depth, Tf, last, hit};
}

torch::Tensor backward(torch::Tensor P, torch::Tensor dirs, torch::Tensor bbox, torch::Tensor toff,
                       torch::Tensor tlist, int64_t H, int64_t W, int64_t ts, torch::Tensor gcol, torch::Tensor gdep,
                       torch::Tensor galpha, torch::Tensor Tf, torch::Tensor last, torch::Tensor hit) {
  const int64_t nv = P.size(0), npairs = tlist.size(0);
  const int nt = threads_for(npairs, (int)ts);
  auto pgrad = torch::empty({npairs, PACK - 1}, P.options());
  auto written = torch::zeros({npairs}, torch::kUInt8);
  const bool da = gdep.any().item<bool>() || galpha.any().item<bool>();  // NaN counts as non-zero
  AT_DISPATCH_FLOATING_TYPES(P.scalar_type(), "splat_backward", [&] {
    (da ? backward_impl<scalar_t, true> : backward_impl<scalar_t, false>)(dirs.data_ptr<scalar_t>(), P.data_ptr<scalar_t>(), bbox.data_ptr<int32_t>(),
                            toff.data_ptr<int64_t>(), tlist.data_ptr<int32_t>(), (int)H, (int)W, (int)ts,
                            gcol.data_ptr<scalar_t>(), gdep.data_ptr<scalar_t>(), galpha.data_ptr<scalar_t>(),
                            Tf.data_ptr<scalar_t>(), last.data_ptr<int32_t>(), hit.data_ptr<uint8_t>(), nt,
                            pgrad.data_ptr<scalar_t>(), written.data_ptr<uint8_t>());
  });
  auto gP = torch::empty({nv, PACK}, P.options());
  AT_DISPATCH_FLOATING_TYPES(P.scalar_type(), "splat_backward_reduce", [&] {
    reduce_pairs<scalar_t>(pgrad.data_ptr<scalar_t>(), written.data_ptr<uint8_t>(), tlist.data_ptr<int32_t>(), npairs,
                           nv, nv < 4096 ? 1 : nthreads(), gP.data_ptr<scalar_t>());
  });
  return gP;
}


// ---------------------------------------------------------------------------
// Fused CPU path: projection + depth sort + binning + rasterisation in one call,
// and the matching backward (projection gradients written by hand).

proj::Cam make_cam(torch::Tensor camv) {
  auto c = camv.to(torch::kFloat64).contiguous();
  const double* v = c.data_ptr<double>();
  proj::Cam cam;
  cam.kind = (int)v[0]; cam.H = (int)v[1]; cam.W = (int)v[2];
  cam.sx = v[3]; cam.sy = v[4]; cam.cx = v[5]; cam.cy = v[6]; cam.eps = v[7]; cam.near = v[8];
  return cam;
}

// World-to-camera rotation (row-major) and translation out of a 4x4 viewmat.
template <typename T>
void split_viewmat(const torch::Tensor& vm, T* R, T* t) {
  auto acc = vm.accessor<T, 2>();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) R[3 * i + j] = acc[i][j];
    t[i] = acc[i][3];
  }
}

template <typename T>
void project_all(const proj::Cam& cam, const T* Rv, const T* tv, const T* means, const T* quats, const T* scales,
                 const T* opac, const T* rgb, int64_t N, T* P, int32_t* bbox, bool* valid, int32_t* radii, T* m2d,
                 T* rot) {
  const int nt = N < 4096 ? 1 : nthreads();
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int64_t g = 0; g < N; ++g) {
    proj::State<T> st;
    proj::forward_one<T>(cam, Rv, tv, means + 3 * g, quats + 4 * g, scales + 3 * g, opac[g], st);
    T* p = P + g * PACK;
    int32_t* b = bbox + 4 * g;
    T* r = rot + 4 * g;
    r[0] = 1; r[1] = 0; r[2] = 0; r[3] = 1;
    if (cam.kind == 0) {
      for (int j = 0; j < 3; ++j) { p[j] = (T)cam.sx * st.e1[j]; p[3 + j] = (T)cam.sy * st.e2[j]; p[6 + j] = st.n[j]; }
    } else {
      p[0] = (T)cam.sx; p[1] = 0; p[2] = 0; p[3] = 0; p[4] = (T)cam.sy; p[5] = 0; p[6] = 0; p[7] = 0; p[8] = 1;
    }
    p[9] = st.uc; p[10] = st.vc; p[11] = st.Q[0]; p[12] = st.Q[1]; p[13] = st.Q[2]; p[14] = opac[g];
    p[15] = rgb[3 * g]; p[16] = rgb[3 * g + 1]; p[17] = rgb[3 * g + 2]; p[18] = st.dist; p[19] = st.tau;
    bool ok = st.valid;
    double radius = 0, phi = 0, theta = std::numeric_limits<double>::quiet_NaN();
    bool have_angles = false;  // longitude / latitude of the centre, from equirect_box
    if (ok) {
      const double A = st.A, B = st.B, C = st.C, tau = st.tau;
      const double lmax = 0.5 * (A + C) + std::sqrt(std::max(0.25 * (A - C) * (A - C) + B * B, 0.0));
      radius = std::sqrt(std::max(2.0 * tau * lmax, 0.0));
      ok = std::isfinite(radius);
      if (ok && cam.kind == 0) {
        double n[3] = {(double)st.n[0], (double)st.n[1], (double)st.n[2]}, e[3], s[3];
        proj::east_south<double>(n, e, s);
        const double e1e = st.e1[0] * e[0] + st.e1[1] * e[1] + st.e1[2] * e[2];
        const double e1s = st.e1[0] * s[0] + st.e1[1] * s[1] + st.e1[2] * s[2];
        const double e2e = st.e2[0] * e[0] + st.e2[1] * e[1] + st.e2[2] * e[2];
        const double e2s = st.e2[0] * s[0] + st.e2[1] * s[1] + st.e2[2] * s[2];
        r[0] = (T)e1e; r[1] = (T)e1s; r[2] = (T)e2e; r[3] = (T)e2s;
        const double see = e1e * e1e * A + 2 * e1e * e2e * B + e2e * e2e * C;
        const double sss = e1s * e1s * A + 2 * e1s * e2s * B + e2s * e2s * C;
        const double hx = std::sqrt(std::max(2.0 * tau * see, 0.0)) / cam.sx;
        const double hy = std::sqrt(std::max(2.0 * tau * sss, 0.0)) / cam.sy;
        ok = proj::equirect_box(cam, n, hx, hy, b, phi, theta);
        have_angles = true;
      } else if (ok) {
        const double hx = std::sqrt(std::max(2.0 * tau * A, 0.0)), hy = std::sqrt(std::max(2.0 * tau * C, 0.0));
        ok = proj::pinhole_box(cam, st.uc + cam.cx, st.vc + cam.cy, hx, hy, b);
      }
    }
    if (!ok) { b[0] = 0; b[1] = -1; b[2] = 0; b[3] = 0; }
    valid[g] = ok;
    radii[g] = ok ? (int32_t)std::ceil(radius) : 0;
    if (cam.kind == 0) {
      if (!have_angles) phi = proj::angle((double)st.n[0], (double)st.n[2]);
      if (!(theta == theta)) {  // NaN: not needed by the box; means2d needs only precision T
        const double x = st.n[0], y = st.n[1], z = st.n[2];
        theta = proj::angle(-y, std::sqrt(x * x + z * z));
      }
      m2d[2 * g] = (T)((phi / (2 * proj::PI) + 0.5) * cam.W - 0.5);
      m2d[2 * g + 1] = (T)((0.5 - theta / proj::PI) * cam.H - 0.5);
    } else {
      m2d[2 * g] = st.uc + (T)cam.cx;
      m2d[2 * g + 1] = st.vc + (T)cam.cy;
    }
  }
}

// Front-to-back order of the visible Gaussians: a stable LSD radix sort of their depth keys
// (splatting/project.py depth_key: the distance's float32 bit pattern, positive floats order
// like their bits, rounded to DEPTH_KEY_SHIFT fewer mantissa bits so that every backend orders
// equal distances alike), one byte per pass, skipping bytes all keys share. Ties keep index
// order, as a sort of (key, index) pairs would; several times faster than std::sort on 100k keys.
#ifndef DEPTH_KEY_SHIFT
#error "DEPTH_KEY_SHIFT comes from splatting/project.py (raster_cpp passes it)"
#endif
template <typename T>
torch::Tensor depth_order_impl(const T* P, const bool* valid, int64_t N) {
  using K = uint32_t;
  constexpr int NB = sizeof(K);  // byte digits
  std::vector<K> key(N), key2;
  std::vector<int64_t> idx(N), idx2;
  int64_t n = 0;
  for (int64_t g = 0; g < N; ++g) {  // branch-free compaction of the visible ones
    const float dist = (float)P[g * PACK + 18];
    K bits;
    std::memcpy(&bits, &dist, sizeof(K));
    key[n] = (bits + (K(1) << (DEPTH_KEY_SHIFT - 1))) >> DEPTH_KEY_SHIFT;
    idx[n] = g;
    n += valid[g];
  }
  key.resize(n);
  idx.resize(n);
  key2.resize(n);
  idx2.resize(n);
  std::vector<int64_t> hist(NB * 256, 0);  // all digits' histograms in one pass
  for (int64_t i = 0; i < n; ++i)
    for (int d = 0; d < NB; ++d) hist[d * 256 + ((key[i] >> (8 * d)) & 255)]++;
  for (int d = 0; d < NB; ++d) {
    int64_t* h = hist.data() + d * 256;
    if (n == 0 || h[(key[0] >> (8 * d)) & 255] == n) continue;  // one digit value: nothing to do
    int64_t sum = 0;
    for (int b = 0; b < 256; ++b) {
      const int64_t c = h[b];
      h[b] = sum;
      sum += c;
    }
    for (int64_t i = 0; i < n; ++i) {
      const int64_t at = h[(key[i] >> (8 * d)) & 255]++;
      key2[at] = key[i];
      idx2[at] = idx[i];
    }
    key.swap(key2);
    idx.swap(idx2);
  }
  auto order = torch::empty({n}, torch::kInt64);
  std::memcpy(order.data_ptr<int64_t>(), idx.data(), n * sizeof(int64_t));
  return order;
}

torch::Tensor depth_order(const torch::Tensor& P, const torch::Tensor& valid) {
  torch::Tensor order;
  AT_DISPATCH_FLOATING_TYPES(P.scalar_type(), "depth_order", [&] {
    order = depth_order_impl<scalar_t>(P.data_ptr<scalar_t>(), valid.data_ptr<bool>(), P.size(0));
  });
  return order;
}

std::vector<torch::Tensor> render_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                          torch::Tensor opac, torch::Tensor rgb, torch::Tensor viewmat,
                                          torch::Tensor dirs, torch::Tensor camv, int64_t ts) {
  TORCH_CHECK(ts >= 1 && ts <= MAX_TILE, "tile size must be 1..32");
  const proj::Cam cam = make_cam(camv);
  const int64_t N = means.size(0), H = cam.H, W = cam.W;
  auto opts = means.options();
  auto P = torch::empty({N, PACK}, opts);
  auto bbox = torch::empty({N, 4}, torch::kInt32);
  auto valid = torch::empty({N}, torch::kBool);
  auto radii = torch::empty({N}, torch::kInt32);
  auto m2d = torch::empty({N, 2}, opts);
  auto rot = torch::empty({N, 4}, opts);
  auto vm = viewmat.contiguous();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project", [&] {
    scalar_t R[9], tv[3];
    split_viewmat<scalar_t>(vm, R, tv);
    project_all<scalar_t>(cam, R, tv, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                          scales.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(), rgb.data_ptr<scalar_t>(), N,
                          P.data_ptr<scalar_t>(), bbox.data_ptr<int32_t>(), valid.data_ptr<bool>(),
                          radii.data_ptr<int32_t>(), m2d.data_ptr<scalar_t>(), rot.data_ptr<scalar_t>());
  });
  auto order = depth_order(P, valid);
  auto bins = bin_gaussians(bbox, order, H, W, ts);
  auto out = forward(P, dirs, bbox, bins[0], bins[1], H, W, ts);
  // color, depth, Tfinal, last, P, bbox, toff, tlist, valid, radii, m2d, rot, hit
  return {out[0], out[1], out[2], out[3], P, bbox, bins[0], bins[1], valid, radii, m2d, rot, out[4]};
}

template <typename T>
void project_backward_all(const proj::Cam& cam, const T* Rv, const T* tv, const T* means, const T* quats,
                          const T* scales, const T* opac, const bool* valid, const T* rot, const T* gP, int64_t N,
                          T* gmeans, T* gquats, T* gscales, T* gopac, T* grgb, T* gm2d, double* gview /*[nt,12]*/) {
  const int nt = N < 4096 ? 1 : nthreads();
#pragma omp parallel num_threads(nt)
  {
    double* gv = gview + 12 * omp_get_thread_num();
#pragma omp for schedule(static)
    for (int64_t g = 0; g < N; ++g) {
      const T* G = gP + g * PACK;
      T* gm = gmeans + 3 * g;
      T* gq = gquats + 4 * g;
      T* gs = gscales + 3 * g;
      gm[0] = gm[1] = gm[2] = 0; gq[0] = gq[1] = gq[2] = gq[3] = 0; gs[0] = gs[1] = gs[2] = 0;
      gopac[g] = 0; grgb[3 * g] = grgb[3 * g + 1] = grgb[3 * g + 2] = 0; gm2d[2 * g] = gm2d[2 * g + 1] = 0;
      if (!valid[g]) continue;
      proj::State<T> st;
      proj::forward_one<T>(cam, Rv, tv, means + 3 * g, quats + 4 * g, scales + 3 * g, opac[g], st);
      gopac[g] = G[14];
      grgb[3 * g] = G[15]; grgb[3 * g + 1] = G[16]; grgb[3 * g + 2] = G[17];
      const T* r = rot + 4 * g;
      gm2d[2 * g] = r[0] * G[9] + r[2] * G[10];
      gm2d[2 * g + 1] = r[1] * G[9] + r[3] * G[10];
      // conic -> covariance: dL/dΣ = -Q Gm Q, Gm = [[g00, g01/2], [g01/2, g11]]
      const T q00 = st.Q[0], q01 = st.Q[1], q11 = st.Q[2];
      const T g00 = G[11], g01 = 0.5 * G[12], g11 = G[13];
      // X = Gm Q
      const T x00 = g00 * q00 + g01 * q01, x01 = g00 * q01 + g01 * q11;
      const T x10 = g01 * q00 + g11 * q01, x11 = g01 * q01 + g11 * q11;
      const T s00 = -(q00 * x00 + q01 * x10), s01 = -(q00 * x01 + q01 * x11), s11 = -(q01 * x01 + q11 * x11);
      const T gA = s00, gC = s11, gB = 2 * s01;
      const T* p = st.m2;
      const T* q = st.m2 + 3;
      T gp[3], gqv[3];
      for (int j = 0; j < 3; ++j) { gp[j] = 2 * gA * p[j] + gB * q[j]; gqv[j] = 2 * gC * q[j] + gB * p[j]; }
      // M2 rows = T2_k L  ->  gT2_k = L gm2_k, gL += T2_kᵀ gm2_k
      T gT2[6];
      for (int i = 0; i < 3; ++i) {
        gT2[i] = st.L[3 * i] * gp[0] + st.L[3 * i + 1] * gp[1] + st.L[3 * i + 2] * gp[2];
        gT2[3 + i] = st.L[3 * i] * gqv[0] + st.L[3 * i + 1] * gqv[1] + st.L[3 * i + 2] * gqv[2];
      }
      T T2[6];
      T gt[3] = {0, 0, 0};
      if (cam.kind == 0) {
        const T k1 = (T)cam.sx / st.dist, k2 = (T)cam.sy / st.dist;
        for (int j = 0; j < 3; ++j) { T2[j] = st.e1[j] * k1; T2[3 + j] = st.e2[j] * k2; }
        T ge1[3], ge2[3];
        for (int j = 0; j < 3; ++j) {
          ge1[j] = gT2[j] * k1 + (T)cam.sx * G[j];
          ge2[j] = gT2[3 + j] * k2 + (T)cam.sy * G[3 + j];
        }
        T gdist = G[18];
        for (int j = 0; j < 3; ++j) gdist -= (gT2[j] * T2[j] + gT2[3 + j] * T2[3 + j]) / st.dist;
        const T x = st.n[0], y = st.n[1], sg = st.sign, a = st.a, a2 = a * a;
        T gn[3] = {G[6], G[7], G[8]};
        gn[0] += ge1[0] * sg * 2 * x * a + ge1[1] * sg * y * a - ge1[2] * sg + ge2[0] * y * a;
        gn[1] += ge1[1] * sg * x * a + ge2[0] * x * a + ge2[1] * 2 * y * a - ge2[2];
        gn[2] += ge1[0] * sg * x * x * a2 + ge1[1] * sg * x * y * a2 + ge2[0] * x * y * a2 + ge2[1] * y * y * a2;
        const T ndg = st.n[0] * gn[0] + st.n[1] * gn[1] + st.n[2] * gn[2];
        for (int j = 0; j < 3; ++j) gt[j] = (gn[j] - st.n[j] * ndg) / st.dist + st.n[j] * gdist;
      } else {
        const T z = st.z, sx = (T)cam.sx, sy = (T)cam.sy;
        T2[0] = sx / z; T2[1] = 0; T2[2] = -sx * st.jx / z; T2[3] = 0; T2[4] = sy / z; T2[5] = -sy * st.jy / z;
        T gz = -gT2[0] * sx / (z * z) + gT2[2] * sx * st.jx / (z * z) - gT2[4] * sy / (z * z) +
               gT2[5] * sy * st.jy / (z * z);
        T gjx = -gT2[2] * sx / z, gjy = -gT2[5] * sy / z;
        T gmx = sx * G[9], gmy = sy * G[10];
        if (st.jx == st.mx) gmx += gjx;
        if (st.jy == st.my) gmy += gjy;
        gt[0] += gmx / z; gt[1] += gmy / z;
        gz -= (gmx * st.mx + gmy * st.my) / z;
        gt[2] += gz;
        for (int j = 0; j < 3; ++j) gt[j] += st.n[j] * G[18];
      }
      // L = Rv Rq S
      T gL[9];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) gL[3 * i + j] = T2[i] * gp[j] + T2[3 + i] * gqv[j];
      T M[9], gM[9];  // M = Rq S ; gM = Rvᵀ gL ; gRv += gL Mᵀ
      const T* s = scales + 3 * g;
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) M[3 * i + j] = st.Rq[3 * i + j] * s[j];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          gM[3 * i + j] = Rv[i] * gL[j] + Rv[3 + i] * gL[3 + j] + Rv[6 + i] * gL[6 + j];
          gv[3 * i + j] += (double)(gL[3 * i] * M[3 * j] + gL[3 * i + 1] * M[3 * j + 1] + gL[3 * i + 2] * M[3 * j + 2]);
        }
      T gR[9];
      for (int j = 0; j < 3; ++j) {
        gs[j] = st.Rq[j] * gM[j] + st.Rq[3 + j] * gM[3 + j] + st.Rq[6 + j] * gM[6 + j];
        for (int i = 0; i < 3; ++i) gR[3 * i + j] = gM[3 * i + j] * s[j];
      }
      const T w = st.qn[0], qx = st.qn[1], qy = st.qn[2], qz = st.qn[3];
      T gqn[4];
      gqn[0] = 2 * (-qz * gR[1] + qy * gR[2] + qz * gR[3] - qx * gR[5] - qy * gR[6] + qx * gR[7]);
      gqn[1] = 2 * (qy * gR[1] + qz * gR[2] + qy * gR[3] - 2 * qx * gR[4] - w * gR[5] + qz * gR[6] + w * gR[7] - 2 * qx * gR[8]);
      gqn[2] = 2 * (-2 * qy * gR[0] + qx * gR[1] + w * gR[2] + qx * gR[3] + qz * gR[5] - w * gR[6] + qz * gR[7] - 2 * qy * gR[8]);
      gqn[3] = 2 * (-2 * qz * gR[0] - w * gR[1] + qx * gR[2] + w * gR[3] - 2 * qz * gR[4] + qy * gR[5] + qx * gR[6] + qy * gR[7]);
      const T* q4 = quats + 4 * g;
      const T n2 = q4[0] * q4[0] + q4[1] * q4[1] + q4[2] * q4[2] + q4[3] * q4[3];
      if (n2 > (T)1e-24) {
        const T dot = gqn[0] * st.qn[0] + gqn[1] * st.qn[1] + gqn[2] * st.qn[2] + gqn[3] * st.qn[3];
        for (int i = 0; i < 4; ++i) gq[i] = (gqn[i] - st.qn[i] * dot) * st.qinv;
      } else {
        for (int i = 0; i < 4; ++i) gq[i] = gqn[i] * st.qinv;
      }
      // t = Rv m + tv
      const T* m = means + 3 * g;
      for (int j = 0; j < 3; ++j) gm[j] = Rv[j] * gt[0] + Rv[3 + j] * gt[1] + Rv[6 + j] * gt[2];
      for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) gv[3 * i + j] += (double)(gt[i] * m[j]);
        gv[9 + i] += (double)gt[i];
      }
    }
  }
}

std::vector<torch::Tensor> render_backward(torch::Tensor gcol, torch::Tensor gdep, torch::Tensor galpha,
                                           torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opac, torch::Tensor viewmat, torch::Tensor dirs,
                                           torch::Tensor camv, int64_t ts, torch::Tensor P, torch::Tensor bbox,
                                           torch::Tensor toff, torch::Tensor tlist, torch::Tensor Tf,
                                           torch::Tensor last, torch::Tensor valid, torch::Tensor rot,
                                           torch::Tensor hit) {
  const proj::Cam cam = make_cam(camv);
  const int64_t N = means.size(0);
  auto gP = backward(P, dirs, bbox, toff, tlist, cam.H, cam.W, ts, gcol, gdep, galpha, Tf, last, hit);
  auto opts = means.options();
  auto gmeans = torch::empty({N, 3}, opts), gquats = torch::empty({N, 4}, opts), gscales = torch::empty({N, 3}, opts);
  auto gopac = torch::empty({N}, opts), grgb = torch::empty({N, 3}, opts), gm2d = torch::empty({N, 2}, opts);
  const int ntv = std::max(1, nthreads());
  auto gview = torch::zeros({ntv, 12}, torch::kFloat64);
  auto vm = viewmat.contiguous();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    scalar_t R[9], tv[3];
    split_viewmat<scalar_t>(vm, R, tv);
    project_backward_all<scalar_t>(cam, R, tv, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                   scales.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(), valid.data_ptr<bool>(),
                                   rot.data_ptr<scalar_t>(), gP.data_ptr<scalar_t>(), N,
                                   gmeans.data_ptr<scalar_t>(), gquats.data_ptr<scalar_t>(),
                                   gscales.data_ptr<scalar_t>(), gopac.data_ptr<scalar_t>(),
                                   grgb.data_ptr<scalar_t>(), gm2d.data_ptr<scalar_t>(), gview.data_ptr<double>());
  });
  auto gv = gview.sum(0);
  auto gviewmat = torch::zeros({4, 4}, torch::kFloat64);
  gviewmat.index_put_({torch::indexing::Slice(0, 3), torch::indexing::Slice(0, 3)}, gv.slice(0, 0, 9).view({3, 3}));
  gviewmat.index_put_({torch::indexing::Slice(0, 3), 3}, gv.slice(0, 9, 12));
  return {gmeans, gquats, gscales, gopac, grgb, gviewmat.to(means.scalar_type()), gm2d};
}


// ---------------------------------------------------------------------------
// Separable blur of image planes with zero padding (SSIM's Gaussian window; used by
// gaussians/losses.py on the CPU): a horizontal pass into a scratch plane, then a
// vertical one, each vectorised over the columns. torch's depthwise conv2d takes ~6x as
// long on the CPU for the same 1xK and Kx1 passes.
template <typename T>
void blur_planes(const T* x, T* out, T* tmp, int64_t nplanes, int H, int W, const T* k, int K) {
  const int p = K / 2;
  const int nt = nplanes * H * W < 65536 ? 1 : nthreads();
#pragma omp parallel num_threads(nt)
  {
    std::vector<T> row(W + 2 * p, T(0));
#pragma omp for schedule(static)
    for (int64_t pr = 0; pr < nplanes * H; ++pr) {  // horizontal: one row at a time, padded
      const T* src = x + pr * W;
      std::memcpy(row.data() + p, src, W * sizeof(T));
      T* dst = tmp + pr * W;
#pragma omp simd
      for (int c = 0; c < W; ++c) dst[c] = k[0] * row[c];
      for (int i = 1; i < K; ++i) {
        const T ki = k[i];
        const T* s = row.data() + i;
#pragma omp simd
        for (int c = 0; c < W; ++c) dst[c] += ki * s[c];
      }
    }
#pragma omp for schedule(static)
    for (int64_t pr = 0; pr < nplanes * H; ++pr) {  // vertical: rows outside the plane are zeros
      const int64_t plane = pr / H;
      const int r = (int)(pr % H);
      const T* base = tmp + plane * H * W;
      T* dst = out + pr * W;
      const int i0 = std::max(0, p - r), i1 = std::min(K, H + p - r);
      for (int c = 0; c < W; ++c) dst[c] = 0;
      for (int i = i0; i < i1; ++i) {
        const T ki = k[i];
        const T* s = base + (int64_t)(r + i - p) * W;
#pragma omp simd
        for (int c = 0; c < W; ++c) dst[c] += ki * s[c];
      }
    }
  }
}

torch::Tensor blur_separable(torch::Tensor x, torch::Tensor taps) {
  TORCH_CHECK(x.dim() >= 2 && x.is_contiguous() && !x.is_cuda(), "x must be a contiguous CPU tensor [..., H, W]");
  TORCH_CHECK(taps.dim() == 1 && taps.size(0) % 2 == 1, "taps must be 1-D, of odd length");
  const int64_t H = x.size(-2), W = x.size(-1), nplanes = H * W ? x.numel() / (H * W) : 0;
  auto out = torch::empty_like(x);
  auto tmp = torch::empty_like(x);
  auto k = taps.to(x.scalar_type()).contiguous();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "blur_separable", [&] {
    blur_planes<scalar_t>(x.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), tmp.data_ptr<scalar_t>(), nplanes,
                          (int)H, (int)W, k.data_ptr<scalar_t>(), (int)k.size(0));
  });
  return out;
}

// SSIM (3DGS's: Gaussian window, zero padding) of x against y, [B,C,H,W], and its gradient
// in x, for gaussians/losses.py on the CPU: the elementwise work of each direction in one
// fused pass (done as ~25 image-sized torch operations it cost more than the blurs).
// ssim_forward returns the blurred maps [B,5,C,H,W] (μx, μy, E[x²], E[y²], E[xy]) and
// Σ_pixels S·wt with wt = `weight`[h,w] (per pixel, [H,W]) or 1 if `weight` is empty.
constexpr double SSIM_C1 = 0.01 * 0.01, SSIM_C2 = 0.03 * 0.03;

inline int threads_for_pixels(int64_t n) { return n < 65536 ? 1 : nthreads(); }

// The SSIM terms at one pixel from the five blurred maps (m: μx, stride to the next map).
template <typename T>
struct SsimTerms {
  T mu1, mu2, a1, a2, b1, b2, s;
  SsimTerms(const T* m, int64_t stride, int64_t i) {
    const T C1 = (T)SSIM_C1, C2 = (T)SSIM_C2;
    mu1 = m[i]; mu2 = m[stride + i];
    const T e11 = m[2 * stride + i], e22 = m[3 * stride + i], e12 = m[4 * stride + i];
    a1 = 2 * mu1 * mu2 + C1;                // 2 μx μy + C1
    a2 = 2 * (e12 - mu1 * mu2) + C2;        // 2 σxy + C2
    b1 = mu1 * mu1 + mu2 * mu2 + C1;        // μx² + μy² + C1
    b2 = e11 + e22 - b1 + (C1 + C2);        // σx² + σy² + C2
    s = a1 * a2 / (b1 * b2);
  }
};

template <typename T>
void ssim_inputs(const T* x, const T* y, T* in, int64_t n) {  // x, y, x², y², xy
#pragma omp parallel for simd schedule(static) num_threads(threads_for_pixels(n))
  for (int64_t i = 0; i < n; ++i) {
    const T a = x[i], c = y[i];
    in[i] = a; in[n + i] = c; in[2 * n + i] = a * a; in[3 * n + i] = c * c; in[4 * n + i] = a * c;
  }
}

template <typename T>
double ssim_sum(const T* m, const T* wt, int64_t n, int64_t HW) {
  double total = 0;
#pragma omp parallel for schedule(static) reduction(+ : total) num_threads(threads_for_pixels(n))
  for (int64_t i = 0; i < n; ++i) {
    const T s = SsimTerms<T>(m, n, i).s;
    total += (double)(wt ? s * wt[i % HW] : s);
  }
  return total;
}

// k·(∂S/∂μx, ∂S/∂E[x²], ∂S/∂E[xy]) per pixel (μy, E[y²] are constants), k = scale·wt
template <typename T>
void ssim_dmaps(const T* m, const T* wt, T scale, T* d, int64_t n, int64_t HW) {
#pragma omp parallel for simd schedule(static) num_threads(threads_for_pixels(n))
  for (int64_t i = 0; i < n; ++i) {
    const SsimTerms<T> t(m, n, i);
    const T k = wt ? scale * wt[i % HW] : scale, dd = t.b1 * t.b2;
    d[i] = 2 * k * (t.mu2 * (t.a2 - t.a1) / dd + t.mu1 * t.s / t.b2 - t.mu1 * t.s / t.b1);
    d[n + i] = -k * t.s / t.b2;
    d[2 * n + i] = 2 * k * t.a1 / dd;
  }
}

template <typename T>
void ssim_grad(const T* g, const T* x, const T* y, T* out, int64_t n) {
#pragma omp parallel for simd schedule(static) num_threads(threads_for_pixels(n))
  for (int64_t i = 0; i < n; ++i) out[i] = g[i] + 2 * x[i] * g[n + i] + y[i] * g[2 * n + i];
}

std::vector<torch::Tensor> ssim_forward(torch::Tensor x, torch::Tensor y, torch::Tensor taps, torch::Tensor weight) {
  TORCH_CHECK(x.dim() == 4 && x.sizes() == y.sizes() && x.is_contiguous() && y.is_contiguous() &&
              x.scalar_type() == y.scalar_type(), "x, y: contiguous [B,C,H,W] of one dtype");
  const int64_t B = x.size(0), C = x.size(1), H = x.size(2), W = x.size(3), HW = H * W, CHW = C * HW;
  const bool weighted = weight.numel() > 0;
  auto in = torch::empty({B, 5, C, H, W}, x.options());
  auto wt = weighted ? weight.to(x.scalar_type()).contiguous() : weight;
  double total = 0;
  torch::Tensor maps;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_forward", [&] {
    for (int64_t b = 0; b < B; ++b)
      ssim_inputs<scalar_t>(x.data_ptr<scalar_t>() + b * CHW, y.data_ptr<scalar_t>() + b * CHW,
                            in.data_ptr<scalar_t>() + b * 5 * CHW, CHW);
    maps = blur_separable(in, taps);
    for (int64_t b = 0; b < B; ++b)
      total += ssim_sum<scalar_t>(maps.data_ptr<scalar_t>() + b * 5 * CHW,
                                  weighted ? wt.data_ptr<scalar_t>() : nullptr, CHW, HW);
  });
  return {maps, torch::tensor(total, torch::kFloat64)};
}

// d(scale · Σ_pixels S·wt)/dx from ssim_forward's maps.
torch::Tensor ssim_backward(torch::Tensor x, torch::Tensor y, torch::Tensor maps, torch::Tensor taps,
                            torch::Tensor weight, double scale) {
  const int64_t B = x.size(0), C = x.size(1), H = x.size(2), W = x.size(3), HW = H * W, CHW = C * HW;
  const bool weighted = weight.numel() > 0;
  auto wt = weighted ? weight.to(x.scalar_type()).contiguous() : weight;
  auto d = torch::empty({B, 3, C, H, W}, x.options());
  auto gx = torch::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_backward", [&] {
    for (int64_t b = 0; b < B; ++b)
      ssim_dmaps<scalar_t>(maps.data_ptr<scalar_t>() + b * 5 * CHW, weighted ? wt.data_ptr<scalar_t>() : nullptr,
                           (scalar_t)scale, d.data_ptr<scalar_t>() + b * 3 * CHW, CHW, HW);
    auto bl = blur_separable(d, taps);
    for (int64_t b = 0; b < B; ++b)
      ssim_grad<scalar_t>(bl.data_ptr<scalar_t>() + b * 3 * CHW, x.data_ptr<scalar_t>() + b * CHW,
                          y.data_ptr<scalar_t>() + b * CHW, gx.data_ptr<scalar_t>() + b * CHW, CHW);
  });
  return gx;
}
}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("bin_gaussians", &bin_gaussians, "tile binning");
  m.def("forward", &forward, "rasterise forward");
  m.def("backward", &backward, "rasterise backward");
  m.def("render_forward", &render_forward, "fused projection + rasterisation");
  m.def("render_backward", &render_backward, "fused backward");
  m.def("blur_separable", &blur_separable, "separable blur of image planes, zero padding");
  m.def("ssim_forward", &ssim_forward, "SSIM maps and weighted sum");
  m.def("ssim_backward", &ssim_backward, "SSIM gradient");
}
