// Tiled alpha compositing of projected 2D Gaussians on the CPU: forward and backward.
//
// This file is compiled on first use by baselines/render/kernel.py into a plain shared library
// (no Python or torch headers) and driven through ctypes with raw pointers to contiguous
// tensors. It implements exactly the rules of the dense oracle composite_reference.py
// (DESIGN.md section 3, gsplat's rules):
//
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,    dx = pixel_x - mean_x (pixel centres at j + 0.5)
//   alpha = min(0.999, o exp(-sigma)), skipped when sigma < 0 or alpha < 1/255
//   a pixel stops BEFORE the Gaussian whose contribution would bring transmittance to <= 1e-4
//   image = sum_i f_i alpha_i T_i,  alpha_out = 1 - T_final
//
// Arithmetic mirrors the oracle: sigma and alpha are evaluated in the same operation order in the
// scalar type (the build uses -ffp-contract=off and no FMA, so no fused operation changes the
// rounding), and transmittance is carried in double and rounded to the scalar type where it is
// used, which is what torch.cumprod does on the CPU (it accumulates float products in double).
//
// exp(): float32 uses a fast vectorised exp (`expf_detail`, at most 1 ulp from the C library's
// expf, equal to it in 96% of values; torch's own CPU exp, which the oracle uses, is within 1 ulp
// of expf too). Where o exp(-sigma) lands within 2^-18 (relative) of 1/255 or 0.999, exp is
// recomputed with expf (`alpha_raw`), so the skip and clamp decisions are exactly those of expf;
// test_raster_kernel.py checks both properties on every machine. float64 calls std::exp.
//
// SIMD: the pixel loops work on 8 consecutive pixels of a tile row at a time (kLanes). Two
// implementations of the 8-lane operations exist: AVX2 intrinsics, chosen at run time when the
// CPU has AVX2 (float32), and a portable one on 16-byte GCC/Clang vector types (SSE2, NEON, ...)
// for every other CPU and for float64. Both perform the same IEEE operations in the same order,
// so they give bitwise identical results (tested). The build flags stay portable: only the AVX2
// variant's functions are compiled for AVX2 (a target attribute), and they run only after
// __builtin_cpu_supports("avx2").
//
// Binning (rk_bin_count / rk_bin_fill): the per-tile lists of tiles.bin_gaussians, built by a
// radix sort of the visible Gaussians by depth and a counting sort into tiles (section below).
//
// Work split: tiles of tile_size x tile_size pixels; each tile is processed by one thread,
// Gaussians in the outer loop (front to back), pixels inner. For each row of a Gaussian's
// bounding box inside the tile, only the span of columns where sigma can pass the cutoff is
// visited: the ellipse sigma <= ln(255 o) + margin, solved per row in double and widened by a
// bound on the float rounding of sigma plus one pixel (`gather_entry`), so every pixel the exact
// per-pixel test could accept is visited; the exact test still decides. Each pixel sees its
// Gaussians in the same front-to-back order, so its arithmetic is that of a pixel-major loop.
// The section "Per-tile blocks" explains how the loops are staged for the CPU.
//
// Backward walks each pixel's list back to front from its last contributor, recovering the
// transmittance by division (T_i = T_{i+1} / (1 - alpha_i), as 3DGS and gsplat do; in double).
// Instead of per-channel sums of f w behind the current Gaussian it carries one per pixel,
// S = sum_{j behind} w_j <g_image, f_j>, which is all the alpha gradient needs (g_image is fixed
// per pixel): this removes C doubles of state and work per pair.
//
// Determinism across thread counts: the backward pass writes one gradient slot per (tile,
// Gaussian) intersection, i.e. per entry of the tile lists. A slot is written only by the thread
// that owns the tile; within the tile, each of the 8 lanes sums its pixels in a fixed order and
// the lanes are added in a fixed order, both given by the tile geometry alone. The slots are then
// reduced per Gaussian in increasing intersection index (= increasing tile index), with Gaussians
// partitioned across threads. Every sum therefore has a fixed order that does not depend on how
// many threads run or which thread took which tile, so 1 and 2 threads give bitwise identical
// gradients. Per-thread gradient buffers would not: their reduction order depends on the thread
// count and the dynamic tile schedule. Memory cost: (6 + C) scalars per intersection.
//
// Threads: std::thread with an atomic tile counter (dynamic schedule, tiles vary widely in cost).
// std::thread rather than OpenMP avoids loading a second OpenMP runtime next to torch's.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#include <system_error>
#include <thread>
#include <type_traits>
#include <vector>

#if (defined(__x86_64__) || defined(__i386__)) && (defined(__GNUC__) || defined(__clang__))
#define RK_HAVE_AVX2 1
#include <immintrin.h>
#else
#define RK_HAVE_AVX2 0
#endif

#define RK_INLINE inline __attribute__((always_inline))
#if RK_HAVE_AVX2
// Not always_inline: the generic tile passes that call these are compiled once without AVX2;
// the AVX2 entry functions are `flatten`, which inlines them there.
#define RK_AVX2 inline __attribute__((target("avx2")))
#endif

namespace {

constexpr int kAbiVersion = 2;
constexpr int kLanes = 8;

// Instruction-set variants of the pixel loops (the `isa` argument of the entry points).
constexpr int64_t kIsaAuto = 0;
constexpr int64_t kIsaPortable = 1;
constexpr int64_t kIsaAvx2 = 2;

bool avx2_supported() {
#if RK_HAVE_AVX2
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2");
#else
    return false;
#endif
}

template <typename scalar_t>
struct Rules {
    // Constants rounded to the scalar type, as torch does when it compares a float32 tensor
    // with a Python float.
    static constexpr scalar_t alpha_min = static_cast<scalar_t>(1.0 / 255.0);
    static constexpr scalar_t alpha_max = static_cast<scalar_t>(0.999);
    static constexpr scalar_t transmittance_min = static_cast<scalar_t>(1e-4);
};

// Margin added to the exact cutoff ln(255 o): exp() and the product with o carry relative errors
// of a few 1e-7, i.e. a few 1e-7 in sigma; 1e-3 keeps every borderline pixel for the exact test.
constexpr double kSigmaCutoffMargin = 1e-3;
// Bound on the float32 rounding error of sigma relative to the size of its terms
// (0.5 |a| dx^2 + 0.5 |c| dy^2 + |b dx dy|): about 5 roundings of 2^-24 each; 1e-5 is 20x that.
constexpr double kSigmaRoundingBound = 1e-5;

// ---- exp for float lanes -----------------------------------------------------------------------
//
// A float exp for x in [-87, 0] (Cephes' expf: x = k ln2 + r, |r| <= ln2 / 2, a degree-5
// polynomial, 2^k added to the exponent bits), evaluated with Estrin's scheme for a short
// dependency chain (the pixel loops are latency-bound). Its error is about 1 ulp, like the Sleef
// exp torch uses for the reference on the CPU (which itself differs from the C library's expf
// in about 1% of values). Where the result could move an alpha decision, the tile loops recompute
// exp with the C library's expf (see `alpha_of`). Both SIMD variants run these exact operations.
namespace expf_detail {
constexpr float kLog2e = 1.44269504088896341f;
constexpr float kMagic = 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer in the low bits
constexpr float kLn2Hi = 0.693359375f;  // 9 significant bits: k * kLn2Hi is exact
constexpr float kLn2Lo = -2.12194440e-4f;
constexpr float kP0 = 5.0000001201e-1f, kP1 = 1.6666665459e-1f, kP2 = 4.1665795894e-2f,
                kP3 = 8.3334519073e-3f, kP4 = 1.3981999507e-3f, kP5 = 1.9875691500e-4f;
constexpr float kLowest = -87.0f;  // exp(-87) is still a normal float (so are all results)

// The shared arithmetic; T is float or an 8-lane float vector, I the matching int32 type.
template <typename T, typename Splat>
RK_INLINE T exp_poly(T x, T& k, Splat c) {
    const T t = x * c(kLog2e) + c(kMagic);
    k = t - c(kMagic);
    const T r = (x - k * c(kLn2Hi)) - k * c(kLn2Lo);
    const T z = r * r;
    const T p = ((c(kP0) + c(kP1) * r) + z * (c(kP2) + c(kP3) * r)) + (z * z) * (c(kP4) + c(kP5) * r);
    // exp(r) = 1 + r + p z, with 1 + r split exactly into s + e (Fast2Sum, |r| < 1) so that only
    // the final addition rounds at the scale of the result: about 1% of results then differ from
    // the correctly rounded value (by 1 ulp), against about 10% for ((p z) + r) + 1.
    const T s = c(1.0f) + r;
    const T e = (c(1.0f) - s) + r;
    return s + (e + p * z);  // the caller scales by 2^k
}

// Half-width of the band around the alpha thresholds (relative) in which o exp(-sigma) is
// recomputed with the C library's expf: 2^-18 is 32 float ulp, far beyond the fast exp's error.
constexpr float kThresholdBand = 1.0f / 262144.0f;
}  // namespace expf_detail

// ---- 8-lane operations, portable variant --------------------------------------------------------
//
// Plain arrays of 8 with lane-wise loops (the compiler vectorises them for the target it is
// given). Masks are int32 lanes, 0 or -1. Used for float64 everywhere and for float32 on CPUs
// without AVX2.
namespace portable {

// 8 lanes as parts of the 16-byte vectors every SIMD target has (SSE2, NEON, ...), written with
// the GCC / Clang vector extensions, so the compiler maps them onto the target's registers.
typedef float f4 __attribute__((vector_size(16)));
typedef int32_t i4 __attribute__((vector_size(16)));
typedef uint32_t u4 __attribute__((vector_size(16)));
typedef double d2 __attribute__((vector_size(16)));
typedef int64_t l2 __attribute__((vector_size(16)));

template <typename T>
struct PartOf;
template <>
struct PartOf<float> {
    using type = f4;
};
template <>
struct PartOf<double> {
    using type = d2;
};
template <>
struct PartOf<int32_t> {
    using type = i4;
};

template <typename T>
struct Vec {
    using Part = typename PartOf<T>::type;
    static constexpr int kParts = kLanes * sizeof(T) / sizeof(Part);
    Part p[kParts];
};
using Mask = Vec<int32_t>;  // lanes 0 or -1
using D8 = Vec<double>;

#define RK_EACH_PART(T) for (int i = 0; i < Vec<T>::kParts; ++i)

template <typename T>
RK_INLINE Vec<T> operator+(Vec<T> a, Vec<T> b) { Vec<T> r; RK_EACH_PART(T) r.p[i] = a.p[i] + b.p[i]; return r; }
template <typename T>
RK_INLINE Vec<T> operator-(Vec<T> a, Vec<T> b) { Vec<T> r; RK_EACH_PART(T) r.p[i] = a.p[i] - b.p[i]; return r; }
template <typename T>
RK_INLINE Vec<T> operator*(Vec<T> a, Vec<T> b) { Vec<T> r; RK_EACH_PART(T) r.p[i] = a.p[i] * b.p[i]; return r; }
template <typename T>
RK_INLINE Vec<T> operator/(Vec<T> a, Vec<T> b) { Vec<T> r; RK_EACH_PART(T) r.p[i] = a.p[i] / b.p[i]; return r; }
RK_INLINE Mask operator&(Mask a, Mask b) { Mask r; RK_EACH_PART(int32_t) r.p[i] = a.p[i] & b.p[i]; return r; }
RK_INLINE Mask operator|(Mask a, Mask b) { Mask r; RK_EACH_PART(int32_t) r.p[i] = a.p[i] | b.p[i]; return r; }
RK_INLINE Mask and_not(Mask a, Mask b) { Mask r; RK_EACH_PART(int32_t) r.p[i] = a.p[i] & ~b.p[i]; return r; }  // a & ~b

// The 64-bit lane masks of doubles 2j, 2j + 1 from a Mask, and back.
RK_INLINE l2 double_part(Mask m, int j) {
    const i4 q = m.p[j / 2];
    return j % 2 ? l2{q[2], q[3]} : l2{q[0], q[1]};
}
RK_INLINE Mask from_double_parts(const l2 (&m)[4]) {
    Mask r;
    r.p[0] = i4{static_cast<int32_t>(m[0][0]), static_cast<int32_t>(m[0][1]), static_cast<int32_t>(m[1][0]),
                static_cast<int32_t>(m[1][1])};
    r.p[1] = i4{static_cast<int32_t>(m[2][0]), static_cast<int32_t>(m[2][1]), static_cast<int32_t>(m[3][0]),
                static_cast<int32_t>(m[3][1])};
    return r;
}

// Comparisons (false for NaN, like C++'s and x86's ordered ones) to a Mask.
#define RK_COMPARISON(NAME, OP)                                                                       \
    RK_INLINE Mask NAME(Vec<float> a, Vec<float> b) {                                                 \
        Mask r;                                                                                       \
        RK_EACH_PART(float) r.p[i] = a.p[i] OP b.p[i];                                                \
        return r;                                                                                     \
    }                                                                                                 \
    RK_INLINE Mask NAME(Vec<double> a, Vec<double> b) {                                               \
        l2 m[4];                                                                                      \
        RK_EACH_PART(double) m[i] = a.p[i] OP b.p[i];                                                 \
        return from_double_parts(m);                                                                  \
    }
RK_COMPARISON(ge, >=)
RK_COMPARISON(gt, >)
RK_COMPARISON(le, <=)
RK_COMPARISON(lt, <)
#undef RK_COMPARISON
RK_INLINE Mask lt(Mask a, Mask b) { Mask r; RK_EACH_PART(int32_t) r.p[i] = a.p[i] < b.p[i]; return r; }

// Bitwise selects: a where m, else b.
RK_INLINE Vec<float> select(Mask m, Vec<float> a, Vec<float> b) {
    Vec<float> r;
    RK_EACH_PART(float) r.p[i] = reinterpret_cast<f4>((reinterpret_cast<i4>(a.p[i]) & m.p[i]) | (reinterpret_cast<i4>(b.p[i]) & ~m.p[i]));
    return r;
}
RK_INLINE Vec<double> select(Mask m, Vec<double> a, Vec<double> b) {
    Vec<double> r;
    RK_EACH_PART(double) {
        const l2 q = double_part(m, i);
        r.p[i] = reinterpret_cast<d2>((reinterpret_cast<l2>(a.p[i]) & q) | (reinterpret_cast<l2>(b.p[i]) & ~q));
    }
    return r;
}
RK_INLINE Mask select(Mask m, Mask a, Mask b) { Mask r; RK_EACH_PART(int32_t) r.p[i] = (a.p[i] & m.p[i]) | (b.p[i] & ~m.p[i]); return r; }
template <typename T>
RK_INLINE Vec<T> masked(Mask m, Vec<T> a) { return select(m, a, Vec<T>{}); }  // 0 off m

RK_INLINE bool any(Mask m) {
    const i4 x = m.p[0] | m.p[1];
    return (x[0] | x[1] | x[2] | x[3]) != 0;
}
RK_INLINE int count(Mask m) {
    int n = 0;
    RK_EACH_PART(int32_t) for (int l = 0; l < 4; ++l) n += m.p[i][l] != 0;
    return n;
}
RK_INLINE D8 widen(Vec<float> a) {
    D8 r;
    RK_EACH_PART(float) {
        r.p[2 * i] = d2{static_cast<double>(a.p[i][0]), static_cast<double>(a.p[i][1])};
        r.p[2 * i + 1] = d2{static_cast<double>(a.p[i][2]), static_cast<double>(a.p[i][3])};
    }
    return r;
}
RK_INLINE D8 widen(D8 a) { return a; }
RK_INLINE D8 sqrt(D8 a) { D8 r; RK_EACH_PART(double) r.p[i] = d2{std::sqrt(a.p[i][0]), std::sqrt(a.p[i][1])}; return r; }
// max / min as x86's maxpd / minpd: the second operand where the first is NaN.
RK_INLINE D8 max(D8 a, D8 b) { return select(gt(a, b), a, b); }
RK_INLINE D8 min(D8 a, D8 b) { return select(lt(a, b), a, b); }
// ceil / floor of values of magnitude below 2^31 (the callers clamp first), exact, without a call
// to the C library where the target has no rounding instruction.
RK_INLINE D8 trunc_small(D8 a) {
    D8 r;
    RK_EACH_PART(double) r.p[i] = d2{static_cast<double>(static_cast<int64_t>(a.p[i][0])),
                                     static_cast<double>(static_cast<int64_t>(a.p[i][1]))};
    return r;
}
RK_INLINE D8 ceil_small(D8 a) { const D8 t = trunc_small(a); return t + masked(lt(t, a), D8{{d2{} + 1.0, d2{} + 1.0, d2{} + 1.0, d2{} + 1.0}}); }
RK_INLINE D8 floor_small(D8 a) { const D8 t = trunc_small(a); return t - masked(gt(t, a), D8{{d2{} + 1.0, d2{} + 1.0, d2{} + 1.0, d2{} + 1.0}}); }
// Integral values in int32 range to int32.
RK_INLINE void store_int32(int32_t* p, D8 a) {
    RK_EACH_PART(double) for (int l = 0; l < 2; ++l) p[2 * i + l] = static_cast<int32_t>(a.p[i][l]);
}
// Sum of the 8 lanes in a fixed order (the AVX2 variant adds in the same order):
// ((l0 + l4) + (l2 + l6)) + ((l1 + l5) + (l3 + l7)).
RK_INLINE double hsum(D8 a) {
    const d2 t01 = a.p[0] + a.p[2], t23 = a.p[1] + a.p[3];  // (l0 + l4, l1 + l5), (l2 + l6, l3 + l7)
    const d2 u = t01 + t23;
    return u[0] + u[1];
}
RK_INLINE double hsum(Vec<float> a) { return hsum(widen(a)); }

struct Ops {
    template <typename T>
    using V = Vec<T>;
    using D = D8;
    using M = Mask;
    using DM = Mask;  // selects of doubles take the lane mask directly
    template <typename T>
    static RK_INLINE Vec<T> splat(T x) { Vec<T> r; RK_EACH_PART(T) r.p[i] = typename Vec<T>::Part{} + x; return r; }
    template <typename T>
    static RK_INLINE Vec<T> load(const T* p) { Vec<T> r; std::memcpy(r.p, p, sizeof r.p); return r; }
    template <typename T>
    static RK_INLINE void store(T* p, Vec<T> a) { std::memcpy(p, a.p, sizeof a.p); }
    static RK_INLINE DM dmask(Mask m) { return m; }
    template <typename T>
    static RK_INLINE Vec<T> narrow(D8 a);
    // Lanes whose index lies in [lo, hi].
    static RK_INLINE Mask span(int32_t lo, int32_t hi) {
        const Mask lane{{i4{0, 1, 2, 3}, i4{4, 5, 6, 7}}};
        return and_not(and_not(Mask{{i4{} - 1, i4{} - 1}}, lt(lane, splat(lo))), lt(splat(hi), lane));
    }
    // exp(-sigma): the fast float exp of expf_detail (float32; the lanes are computed as the AVX2
    // variant computes them), std::exp on the active lanes (float64).
    static RK_INLINE Vec<float> exp_neg(Vec<float> sigma, Mask) {
        using namespace expf_detail;
        Vec<float> r;
        RK_EACH_PART(float) {
            f4 x = -sigma.p[i];
            x = reinterpret_cast<f4>((reinterpret_cast<i4>(x) & (x > kLowest)) |
                                     (reinterpret_cast<i4>(f4{} + kLowest) & ~(x > kLowest)));  // NaN -> kLowest
            f4 k;
            const f4 y = exp_poly(x, k, [](float v) { return f4{} + v; });
            const u4 scale = u4{static_cast<uint32_t>(static_cast<int32_t>(k[0])), static_cast<uint32_t>(static_cast<int32_t>(k[1])),
                                static_cast<uint32_t>(static_cast<int32_t>(k[2])), static_cast<uint32_t>(static_cast<int32_t>(k[3]))}
                             << 23;
            r.p[i] = reinterpret_cast<f4>(reinterpret_cast<u4>(y) + scale);
        }
        return r;
    }
    static RK_INLINE Vec<double> exp_neg(Vec<double> sigma, Mask active) {
        Vec<double> r;
        RK_EACH_PART(double) {
            const l2 q = double_part(active, i);
            r.p[i] = d2{q[0] ? std::exp(-sigma.p[i][0]) : 0.0, q[1] ? std::exp(-sigma.p[i][1]) : 0.0};
        }
        return r;
    }
    static RK_INLINE int bits(Mask m) {
        int b = 0;
        RK_EACH_PART(int32_t) for (int l = 0; l < 4; ++l) b |= (m.p[i][l] != 0) << (4 * i + l);
        return b;
    }
};
template <>
RK_INLINE Vec<float> Ops::narrow<float>(D8 a) {
    Vec<float> r;
    RK_EACH_PART(float) r.p[i] = f4{static_cast<float>(a.p[2 * i][0]), static_cast<float>(a.p[2 * i][1]),
                                    static_cast<float>(a.p[2 * i + 1][0]), static_cast<float>(a.p[2 * i + 1][1])};
    return r;
}
template <>
RK_INLINE Vec<double> Ops::narrow<double>(D8 a) { return a; }

#undef RK_EACH_PART
}  // namespace portable

// ---- 8-lane operations, AVX2 variant (float32 only) --------------------------------------------
#if RK_HAVE_AVX2
namespace avx2 {

struct F8 {
    __m256 v;
};
struct I8 {  // int32 lanes; masks are 0 or -1
    __m256i v;
};
struct D8 {  // lanes 0-3 in lo, 4-7 in hi
    __m256d lo, hi;
};
struct DM8 {  // a mask widened to 64-bit lanes for selecting doubles
    __m256d lo, hi;
};

RK_AVX2 F8 operator+(F8 a, F8 b) { return {_mm256_add_ps(a.v, b.v)}; }
RK_AVX2 F8 operator-(F8 a, F8 b) { return {_mm256_sub_ps(a.v, b.v)}; }
RK_AVX2 F8 operator*(F8 a, F8 b) { return {_mm256_mul_ps(a.v, b.v)}; }
RK_AVX2 D8 operator+(D8 a, D8 b) { return {_mm256_add_pd(a.lo, b.lo), _mm256_add_pd(a.hi, b.hi)}; }
RK_AVX2 D8 operator-(D8 a, D8 b) { return {_mm256_sub_pd(a.lo, b.lo), _mm256_sub_pd(a.hi, b.hi)}; }
RK_AVX2 D8 operator*(D8 a, D8 b) { return {_mm256_mul_pd(a.lo, b.lo), _mm256_mul_pd(a.hi, b.hi)}; }
RK_AVX2 D8 operator/(D8 a, D8 b) { return {_mm256_div_pd(a.lo, b.lo), _mm256_div_pd(a.hi, b.hi)}; }
RK_AVX2 I8 operator&(I8 a, I8 b) { return {_mm256_and_si256(a.v, b.v)}; }
RK_AVX2 I8 operator|(I8 a, I8 b) { return {_mm256_or_si256(a.v, b.v)}; }
RK_AVX2 I8 and_not(I8 a, I8 b) { return {_mm256_andnot_si256(b.v, a.v)}; }  // a & ~b
// Ordered, non-signalling comparisons: false for NaN, like C++'s >= and <=.
RK_AVX2 I8 ge(F8 a, F8 b) { return {_mm256_castps_si256(_mm256_cmp_ps(a.v, b.v, _CMP_GE_OQ))}; }
RK_AVX2 I8 gt(F8 a, F8 b) { return {_mm256_castps_si256(_mm256_cmp_ps(a.v, b.v, _CMP_GT_OQ))}; }
RK_AVX2 I8 le(F8 a, F8 b) { return {_mm256_castps_si256(_mm256_cmp_ps(a.v, b.v, _CMP_LE_OQ))}; }
RK_AVX2 I8 lt(I8 a, I8 b) { return {_mm256_cmpgt_epi32(b.v, a.v)}; }
RK_AVX2 DM8 lt(D8 a, D8 b) { return {_mm256_cmp_pd(a.lo, b.lo, _CMP_LT_OQ), _mm256_cmp_pd(a.hi, b.hi, _CMP_LT_OQ)}; }
RK_AVX2 F8 select(I8 m, F8 a, F8 b) { return {_mm256_blendv_ps(b.v, a.v, _mm256_castsi256_ps(m.v))}; }
RK_AVX2 I8 select(I8 m, I8 a, I8 b) { return {_mm256_blendv_epi8(b.v, a.v, m.v)}; }
RK_AVX2 D8 select(DM8 m, D8 a, D8 b) { return {_mm256_blendv_pd(b.lo, a.lo, m.lo), _mm256_blendv_pd(b.hi, a.hi, m.hi)}; }
RK_AVX2 F8 masked(I8 m, F8 a) { return {_mm256_and_ps(_mm256_castsi256_ps(m.v), a.v)}; }  // 0 off m
RK_AVX2 D8 masked(DM8 m, D8 a) { return {_mm256_and_pd(m.lo, a.lo), _mm256_and_pd(m.hi, a.hi)}; }
RK_AVX2 bool any(I8 m) { return !_mm256_testz_si256(m.v, m.v); }
RK_AVX2 int count(I8 m) { return __builtin_popcount(static_cast<unsigned>(_mm256_movemask_ps(_mm256_castsi256_ps(m.v)))); }
RK_AVX2 D8 widen(F8 a) {
    return {_mm256_cvtps_pd(_mm256_castps256_ps128(a.v)), _mm256_cvtps_pd(_mm256_extractf128_ps(a.v, 1))};
}
RK_AVX2 D8 sqrt(D8 a) { return {_mm256_sqrt_pd(a.lo), _mm256_sqrt_pd(a.hi)}; }
RK_AVX2 D8 floor_small(D8 a) { return {_mm256_floor_pd(a.lo), _mm256_floor_pd(a.hi)}; }
RK_AVX2 D8 ceil_small(D8 a) { return {_mm256_ceil_pd(a.lo), _mm256_ceil_pd(a.hi)}; }
RK_AVX2 D8 max(D8 a, D8 b) { return {_mm256_max_pd(a.lo, b.lo), _mm256_max_pd(a.hi, b.hi)}; }
RK_AVX2 D8 min(D8 a, D8 b) { return {_mm256_min_pd(a.lo, b.lo), _mm256_min_pd(a.hi, b.hi)}; }
RK_AVX2 void store_int32(int32_t* p, D8 a) {
    _mm_storeu_si128(reinterpret_cast<__m128i*>(p), _mm256_cvttpd_epi32(a.lo));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(p + 4), _mm256_cvttpd_epi32(a.hi));
}
RK_AVX2 double hsum(D8 a);
RK_AVX2 double hsum(F8 a) { return hsum(widen(a)); }
RK_AVX2 double hsum(D8 a) {  // the order of portable::hsum
    const __m256d t = _mm256_add_pd(a.lo, a.hi);                                   // t0 t1 t2 t3
    const __m128d u = _mm_add_pd(_mm256_castpd256_pd128(t), _mm256_extractf128_pd(t, 1));  // t0+t2, t1+t3
    return _mm_cvtsd_f64(_mm_add_sd(u, _mm_unpackhi_pd(u, u)));
}

struct SplatF8 {  // (a functor rather than a lambda: portable across compilers with the attribute)
    RK_AVX2 F8 operator()(float v) const { return {_mm256_set1_ps(v)}; }
};

struct Ops {
    template <typename T>
    using V = F8;  // float32 only
    using D = D8;
    using M = I8;
    using DM = DM8;
    template <typename T>
    static RK_AVX2 F8 splat(float x) { return {_mm256_set1_ps(x)}; }
    static RK_AVX2 I8 splat(int32_t x) { return {_mm256_set1_epi32(x)}; }
    static RK_AVX2 D8 splat(double x) { return {_mm256_set1_pd(x), _mm256_set1_pd(x)}; }
    static RK_AVX2 F8 load(const float* p) { return {_mm256_loadu_ps(p)}; }
    static RK_AVX2 I8 load(const int32_t* p) { return {_mm256_loadu_si256(reinterpret_cast<const __m256i*>(p))}; }
    static RK_AVX2 D8 load(const double* p) { return {_mm256_loadu_pd(p), _mm256_loadu_pd(p + 4)}; }
    static RK_AVX2 void store(float* p, F8 a) { _mm256_storeu_ps(p, a.v); }
    static RK_AVX2 int bits(I8 m) { return _mm256_movemask_ps(_mm256_castsi256_ps(m.v)); }
    static RK_AVX2 void store(int32_t* p, I8 a) { _mm256_storeu_si256(reinterpret_cast<__m256i*>(p), a.v); }
    static RK_AVX2 void store(double* p, D8 a) { _mm256_storeu_pd(p, a.lo); _mm256_storeu_pd(p + 4, a.hi); }
    static RK_AVX2 DM8 dmask(I8 m) {
        return {_mm256_castsi256_pd(_mm256_cvtepi32_epi64(_mm256_castsi256_si128(m.v))),
                _mm256_castsi256_pd(_mm256_cvtepi32_epi64(_mm256_extracti128_si256(m.v, 1)))};
    }
    template <typename T>
    static RK_AVX2 F8 narrow(D8 a) {
        return {_mm256_insertf128_ps(_mm256_castps128_ps256(_mm256_cvtpd_ps(a.lo)), _mm256_cvtpd_ps(a.hi), 1)};
    }
    static RK_AVX2 I8 span(int32_t lo, int32_t hi) {
        const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        const __m256i outside = _mm256_or_si256(_mm256_cmpgt_epi32(_mm256_set1_epi32(lo), lane),
                                                _mm256_cmpgt_epi32(lane, _mm256_set1_epi32(hi)));
        return {_mm256_andnot_si256(outside, _mm256_set1_epi32(-1))};
    }
    static RK_AVX2 F8 exp_neg(F8 sigma, I8) {
        using namespace expf_detail;
        const __m256 x = _mm256_max_ps(_mm256_xor_ps(sigma.v, _mm256_set1_ps(-0.0f)), _mm256_set1_ps(kLowest));
        F8 k;
        const F8 y = exp_poly(F8{x}, k, SplatF8{});
        const __m256i scale = _mm256_slli_epi32(_mm256_cvttps_epi32(k.v), 23);
        return {_mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(y.v), scale))};
    }
};

}  // namespace avx2
#endif  // RK_HAVE_AVX2

// ---- Problem description ---------------------------------------------------------------------

struct Problem {
    const void* means2d;   // [N, 2]
    const void* conics;    // [N, 3]
    const void* opacities; // [N]
    const void* features;  // [N, C]
    const int32_t* radii;  // [N, 2]
    int64_t num_gaussians;
    int64_t channels;
    const int64_t* offsets;      // [tiles + 1]
    const int64_t* gaussian_ids; // [M]
    int64_t width;
    int64_t height;
    int64_t tile_size;
    int64_t tiles_x;
    int64_t tiles_y;
    int64_t row_stride;  // tile-local buffers: tile_size rounded up to a multiple of kLanes
};

struct TileRect {
    int64_t x0, y0, x1, y1;  // pixel rectangle [x0, x1) x [y0, y1)
    int64_t width() const { return x1 - x0; }
    int64_t rows() const { return y1 - y0; }
};

TileRect tile_rect(const Problem& p, int64_t tile) {
    const int64_t tx = tile % p.tiles_x;
    const int64_t ty = tile / p.tiles_x;
    TileRect r;
    r.x0 = tx * p.tile_size;
    r.y0 = ty * p.tile_size;
    r.x1 = std::min(r.x0 + p.tile_size, p.width);
    r.y1 = std::min(r.y0 + p.tile_size, p.height);
    return r;
}

// One Gaussian's screen-space parameters, prepared once per pass (not once per tile).
template <typename scalar_t>
struct Splat {
    scalar_t mx, my, a, b, c, o;
    scalar_t cut;       // the sigma pre-filter in the scalar type: largest value <= sigma_cutoff
    bool never;         // no pixel can pass (o = 0)
    bool span_ok;       // row spans can be solved from the conic (a > 0, all finite)
    double span_c2a;    // 2 a cut' (cut' = sigma_cutoff widened by the rounding bound)
    double det;         // a c - b^2
    double b_over_a, inv_a, centre_x;  // centre_x = mx - 0.5 (pixel column of the mean)
    double col_lo, col_hi, row_lo, row_hi;  // pixel columns / rows it can reach (unclipped)
    const scalar_t* feature;
};

template <typename scalar_t>
scalar_t round_down(double x) {
    scalar_t y = static_cast<scalar_t>(x);
    if (static_cast<double>(y) > x) y = std::nextafter(y, -std::numeric_limits<scalar_t>::infinity());
    return y;
}

template <typename scalar_t>
Splat<scalar_t> prepare_splat(const Problem& p, int64_t g) {
    const scalar_t* m = static_cast<const scalar_t*>(p.means2d) + 2 * g;
    const scalar_t* q = static_cast<const scalar_t*>(p.conics) + 3 * g;
    Splat<scalar_t> s;
    s.mx = m[0];
    s.my = m[1];
    s.a = q[0];
    s.b = q[1];
    s.c = q[2];
    s.o = static_cast<const scalar_t*>(p.opacities)[g];
    s.feature = static_cast<const scalar_t*>(p.features) + g * p.channels;
    // alpha >= 1/255 needs o exp(-sigma) >= 1/255, i.e. sigma <= ln(255 o) (-inf when o = 0).
    const double sigma_cutoff = std::log(255.0 * static_cast<double>(s.o)) + kSigmaCutoffMargin;
    s.never = !(sigma_cutoff > -std::numeric_limits<double>::infinity());
    // A float sigma compares <= sigma_cutoff exactly when it is <= the cutoff rounded down.
    s.cut = s.never ? scalar_t(0) : round_down<scalar_t>(sigma_cutoff);
    // Pixel centres j + 0.5 within the radius of the mean, plus one pixel of slack per side (the
    // radii bound the alpha >= 1/255 region; the slack absorbs rounding at its edge). Kept in
    // double and clamped to a tile before any conversion, so huge radii cannot overflow.
    const double rx = static_cast<double>(p.radii[2 * g]);
    const double ry = static_cast<double>(p.radii[2 * g + 1]);
    const double mxd = static_cast<double>(s.mx), myd = static_cast<double>(s.my);
    s.col_lo = std::floor(mxd - rx - 0.5);
    s.col_hi = std::ceil(mxd + rx - 0.5);
    s.row_lo = std::floor(myd - ry - 0.5);
    s.row_hi = std::ceil(myd + ry - 0.5);
    // Row spans: in row dy the pixels with exact sigma <= cut' form the interval
    // dx in [(-b dy - root) / a, (-b dy + root) / a], root = sqrt(2 a cut' - dy^2 (a c - b^2)).
    // cut' adds to the cutoff a bound on the rounding of the float sigma over the box
    // (|dx| <= rx + 1, |dy| <= ry + 1), so a pixel whose float sigma passes lies in the span.
    const double a = static_cast<double>(s.a), b = static_cast<double>(s.b), c = static_cast<double>(s.c);
    const double X = rx + 2.0, Y = ry + 2.0;
    const double cut_wide =
        sigma_cutoff + kSigmaRoundingBound * (0.5 * std::fabs(a) * X * X + 0.5 * std::fabs(c) * Y * Y + std::fabs(b) * X * Y);
    s.span_c2a = 2.0 * a * cut_wide;
    s.det = a * c - b * b;
    s.inv_a = 1.0 / a;
    s.b_over_a = b / a;
    s.centre_x = mxd - 0.5;
    s.span_ok = a > 0 && std::isfinite(s.span_c2a) && std::isfinite(s.det) && std::isfinite(s.inv_a) &&
                std::isfinite(s.b_over_a) && std::isfinite(s.centre_x);
    return s;
}

// The pixels of one tile a Gaussian's box can reach (inclusive ranges).
struct Footprint {
    int64_t jlo, jhi, ilo, ihi;
    bool empty() const { return jlo > jhi || ilo > ihi; }
};

template <typename scalar_t>
inline Footprint clip(const Splat<scalar_t>& s, const TileRect& r) {
    Footprint f;
    f.jlo = static_cast<int64_t>(std::max<double>(static_cast<double>(r.x0), s.col_lo));
    f.jhi = static_cast<int64_t>(std::min<double>(static_cast<double>(r.x1 - 1), s.col_hi));
    f.ilo = static_cast<int64_t>(std::max<double>(static_cast<double>(r.y0), s.row_lo));
    f.ihi = static_cast<int64_t>(std::min<double>(static_cast<double>(r.y1 - 1), s.row_hi));
    return f;
}

// Runs fn(item, worker) for item in [0, n) on `threads` workers with a dynamic schedule. An
// exception in any worker stops the others and is rethrown here after all have joined; if a
// thread cannot be started, the workers already running finish the items.
void parallel_items(int64_t n, int64_t threads, const std::function<void(int64_t, int64_t)>& fn) {
    threads = std::max<int64_t>(1, std::min<int64_t>(threads, n));
    if (threads == 1) {
        for (int64_t i = 0; i < n; ++i) fn(i, 0);
        return;
    }
    std::atomic<int64_t> next{0};
    std::mutex error_mutex;
    std::exception_ptr error;
    auto worker = [&](int64_t w) {
        try {
            for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i, w);
        } catch (...) {
            std::lock_guard<std::mutex> lock(error_mutex);
            if (!error) error = std::current_exception();
            next.store(n);
        }
    };
    std::vector<std::thread> pool;
    pool.reserve(static_cast<size_t>(threads - 1));
    for (int64_t w = 1; w < threads; ++w) {
        try {
            pool.emplace_back(worker, w);
        } catch (const std::system_error&) {
            break;
        }
    }
    worker(0);
    for (auto& t : pool) t.join();
    if (error) std::rethrow_exception(error);
}

// ---- Per-tile blocks of Gaussians --------------------------------------------------------------
//
// The tile passes first gather a block of the tile's list entries into small local arrays (the
// Gaussians' parameters and features, read once from the scattered per-Gaussian arrays with
// independent loads whose cache misses overlap) and solve the row spans of each entry into a flat
// list of 8-pixel chunks. The SIMD work on the chunks then runs in two phases over batches of
// kStageChunks chunks: phase A evaluates sigma, exp and alpha of each chunk (chunks independent
// of each other, no branches on the data path, so the CPU overlaps many of them) and keeps the
// chunks with a lane to composite; phase B walks those in order through the per-pixel state
// (transmittance, sums), whose updates must follow the front-to-back order. One fused loop would
// be bound by the latency of its ~120-cycle dependency chain per chunk.

constexpr int64_t kBlockEntries = 32;
constexpr int64_t kStageChunks = 64;

// 8 pixels of one tile row: tile-local row, column of lane 0, the lanes [lo, hi] to visit, and
// the row's dy = pixel centre y - mean y and c dy dy (the reference's operation order).
template <typename scalar_t>
struct Chunk {
    int32_t entry;  // index in the block
    int32_t row;
    int32_t start;
    int16_t lo, hi;
    scalar_t dy, c_dy_dy;
};

template <typename scalar_t>
struct Block {
    int64_t size = 0;                        // entries
    int64_t num_chunks = 0;
    std::vector<scalar_t> mx, a, b, c, o, cut;
    std::vector<int64_t> k;                  // index in the tile lists (position, slot)
    std::vector<scalar_t> feature;           // [entries][C]
    std::vector<Chunk<scalar_t>> chunks;     // [capacity]
    std::vector<scalar_t> dy;                // per footprint row of the entry being gathered
    std::vector<int32_t> span_lo, span_hi;   // its columns that can pass the cutoff

    void reserve(int64_t channels, int64_t tile_size) {
        for (auto* v : {&mx, &a, &b, &c, &o, &cut}) v->resize(kBlockEntries);
        k.resize(kBlockEntries);
        feature.resize(kBlockEntries * channels);
        const int64_t rows = (tile_size + kLanes - 1) / kLanes * kLanes;
        for (auto* v : {&span_lo, &span_hi}) v->resize(rows);
        dy.assign(rows, scalar_t(0));
        chunks.resize(static_cast<size_t>(kBlockEntries * tile_size * ((tile_size + kLanes - 1) / kLanes + 1)));
    }
    void clear() {
        size = 0;
        num_chunks = 0;
    }
};

// Starts loading the parameters of list entry k, a few entries ahead of gather_entry: they are
// scattered over megabytes, and each entry's own work is too long for the CPU to reach the next
// entry's loads by itself.
template <typename scalar_t>
RK_INLINE void prefetch_entry(const Problem& p, const Splat<scalar_t>* splats, int64_t k) {
    const int64_t g = p.gaussian_ids[k];
    const char* splat = reinterpret_cast<const char*>(splats + g);
    __builtin_prefetch(splat);
    __builtin_prefetch(splat + sizeof(Splat<scalar_t>) - 1);
    __builtin_prefetch(static_cast<const scalar_t*>(p.features) + g * p.channels);
}
constexpr int64_t kPrefetchDistance = 8;

// Appends list entry k (Gaussian splats[ids[k]]) to the block with its chunks; false when it
// cannot touch a pixel of the tile (then nothing is appended).
//
// Row spans: in row dy the pixels with exact sigma <= cut' form the interval dx in
// [(-b dy - root) / a, (-b dy + root) / a], root = sqrt(2 a cut' - dy^2 (a c - b^2)); cut' adds
// to the cutoff a bound on the rounding of the float sigma over the box (see prepare_splat), so
// every pixel whose float sigma passes lies in the span; one pixel of slack per side absorbs the
// rounding of the span itself. Solved for 8 rows at a time; where the conic does not allow it
// (a <= 0, non-finite values) the whole footprint row is visited.
template <typename Ops, typename scalar_t>
inline bool gather_entry(const Problem& p, const Splat<scalar_t>* splats, const TileRect& r, int64_t k,
                         Block<scalar_t>& blk) {
    using D = typename Ops::D;
    const Splat<scalar_t>& g = splats[p.gaussian_ids[k]];
    if (g.never) return false;
    const Footprint fp = clip(g, r);
    if (fp.empty()) return false;
    const int64_t rows = fp.ihi - fp.ilo + 1;
    for (int64_t t = 0; t < rows; ++t)
        blk.dy[t] = (static_cast<scalar_t>(fp.ilo + t) + static_cast<scalar_t>(0.5)) - g.my;
    if (g.span_ok) {
        const D zero = Ops::splat(0.0), one = Ops::splat(1.0);
        const D col_lo = Ops::splat(static_cast<double>(fp.jlo)), col_hi = Ops::splat(static_cast<double>(fp.jhi));
        for (int64_t t = 0; t < rows; t += kLanes) {
            const D dy = widen(Ops::load(static_cast<const scalar_t*>(blk.dy.data() + t)));
            const D disc = Ops::splat(g.span_c2a) - dy * dy * Ops::splat(g.det);
            const D half_width = sqrt(max(disc, zero)) * Ops::splat(g.inv_a);
            const D centre = Ops::splat(g.centre_x) - Ops::splat(g.b_over_a) * dy;
            // Clamped to the footprint (+-1) before rounding: ceil and floor then see small values.
            const D lo = ceil_small(min(max(centre - half_width, col_lo + one), col_hi + one + one)) - one;
            D hi = floor_small(max(min(centre + half_width, col_hi - one), col_lo - one - one)) + one;
            hi = select(lt(disc, zero), col_lo - one, hi);  // no pixel of the row can pass
            store_int32(blk.span_lo.data() + t, lo);
            store_int32(blk.span_hi.data() + t, hi);
        }
    } else {
        std::fill(blk.span_lo.begin(), blk.span_lo.begin() + rows, static_cast<int32_t>(fp.jlo));
        std::fill(blk.span_hi.begin(), blk.span_hi.begin() + rows, static_cast<int32_t>(fp.jhi));
    }
    const int64_t e = blk.size;
    const int64_t last_start = p.row_stride - kLanes;
    Chunk<scalar_t>* out = blk.chunks.data();
    int64_t nc = blk.num_chunks;
    for (int64_t t = 0; t < rows; ++t) {
        const int64_t hi = blk.span_hi[t] - r.x0;
        for (int64_t from = blk.span_lo[t] - r.x0; from <= hi;) {
            const int64_t start = std::min(from, last_start);
            out[nc++] = Chunk<scalar_t>{static_cast<int32_t>(e), static_cast<int32_t>(fp.ilo + t - r.y0),
                                        static_cast<int32_t>(start), static_cast<int16_t>(from - start),
                                        static_cast<int16_t>(std::min<int64_t>(hi - start, kLanes - 1)),
                                        blk.dy[t], g.c * blk.dy[t] * blk.dy[t]};
            from = start + kLanes;
        }
    }
    if (nc == blk.num_chunks) return false;
    blk.num_chunks = nc;
    blk.mx[e] = g.mx;
    blk.a[e] = g.a;
    blk.b[e] = g.b;
    blk.c[e] = g.c;
    blk.o[e] = g.o;
    blk.cut[e] = g.cut;
    blk.k[e] = k;
    scalar_t* f = blk.feature.data() + e * p.channels;
    for (int64_t j = 0; j < p.channels; ++j) f[j] = g.feature[j];  // (a call to memmove costs more)
    blk.size = e + 1;
    return true;
}

// Pixel centres x of each chunk start: (float(x0 + start) + lane) + 0.5 (exact integers, so the
// value is float(j) + 0.5 as in the reference), [start][lane].
template <typename scalar_t>
void pixel_columns(const Problem& p, const TileRect& r, std::vector<scalar_t>& px) {
    px.resize(static_cast<size_t>(p.row_stride * kLanes));
    for (int64_t start = 0; start + kLanes <= p.row_stride; ++start)
        for (int l = 0; l < kLanes; ++l)
            px[start * kLanes + l] = static_cast<scalar_t>(r.x0 + start + l) + static_cast<scalar_t>(0.5);
}

// vis = exp(-sigma) and raw = o vis on the lanes m. For float32 the fast exp is used, except
// where raw falls within a relative band of 2^-18 around 1/255 or 0.999: there exp is recomputed
// with the C library's expf, so the skip and clamp decisions are those of an exact expf (the fast
// exp's ~1 ulp error cannot move raw across a threshold from outside the band).
template <typename Ops, typename scalar_t, typename V, typename M>
RK_INLINE V alpha_raw(V sigma, V o, M m, V& vis) {
    vis = Ops::exp_neg(sigma, m);
    V raw = o * vis;
    if constexpr (std::is_same<scalar_t, float>::value) {
        using R = Rules<float>;
        constexpr float lo = 1.0f - expf_detail::kThresholdBand, hi = 1.0f + expf_detail::kThresholdBand;
        const M near = m & ((ge(raw, Ops::template splat<float>(R::alpha_min * lo)) &
                             le(raw, Ops::template splat<float>(R::alpha_min * hi))) |
                            (ge(raw, Ops::template splat<float>(R::alpha_max * lo)) &
                             le(raw, Ops::template splat<float>(R::alpha_max * hi))));
        if (any(near)) {
            float sig[kLanes], v[kLanes];
            Ops::store(sig, sigma);
            Ops::store(v, vis);
            const int b = Ops::bits(near);
            for (int l = 0; l < kLanes; ++l)
                if (b & (1 << l)) v[l] = std::exp(-sig[l]);
            vis = Ops::load(static_cast<const float*>(v));
            raw = o * vis;
        }
    }
    return raw;
}

// Phase A for one chunk: sigma and alpha on the lanes of `m` (updated to the lanes that pass the
// sigma and alpha tests); also returns vis and whether alpha is below the 0.999 clamp.
template <typename Ops, typename scalar_t>
struct ChunkEval {
    using V = typename Ops::template V<scalar_t>;
    using M = typename Ops::M;
    V dx, vis, alpha;
    M unclamped;
};

template <typename Ops, typename scalar_t>
RK_INLINE ChunkEval<Ops, scalar_t> evaluate_chunk(const Block<scalar_t>& blk, const Chunk<scalar_t>& ch,
                                                  const scalar_t* px, typename Ops::M& m) {
    using V = typename Ops::template V<scalar_t>;
    using R = Rules<scalar_t>;
    const int64_t e = ch.entry;
    ChunkEval<Ops, scalar_t> out;
    out.dx = Ops::load(px + ch.start * kLanes) - Ops::template splat<scalar_t>(blk.mx[e]);
    const V dx = out.dx;
    const V half = Ops::template splat<scalar_t>(0.5);
    const V sigma = half * (Ops::template splat<scalar_t>(blk.a[e]) * dx * dx + Ops::template splat<scalar_t>(ch.c_dy_dy)) +
                    Ops::template splat<scalar_t>(blk.b[e]) * dx * Ops::template splat<scalar_t>(ch.dy);
    m = m & ge(sigma, Ops::template splat<scalar_t>(0)) & le(sigma, Ops::template splat<scalar_t>(blk.cut[e]));
    const V raw = alpha_raw<Ops, scalar_t>(sigma, Ops::template splat<scalar_t>(blk.o[e]), m, out.vis);
    const V alpha_max = Ops::template splat<scalar_t>(R::alpha_max);
    out.unclamped = le(raw, alpha_max);
    const V alpha = select(out.unclamped, raw, alpha_max);
    m = m & ge(alpha, Ops::template splat<scalar_t>(R::alpha_min));
    out.alpha = masked(m, alpha);  // 0 on masked-off lanes: T, w and sums stay exact there
    return out;
}

// ---- Forward ---------------------------------------------------------------------------------

template <typename scalar_t>
struct ForwardOut {
    scalar_t* image;       // [H, W, C]
    scalar_t* alpha;       // [H, W]
    double* transmittance; // [H, W] final T (double, see header)
    int32_t* last;         // [H, W] 1 + position in the tile list of the last contributor (0: none)
};

template <typename scalar_t>
struct ForwardScratch {  // tile-local, row stride Problem::row_stride
    std::vector<double> T, accum;  // accum: [C][pixels]
    std::vector<int32_t> last, done;
    std::vector<scalar_t> px;
    Block<scalar_t> block;
    std::vector<scalar_t> stage_alpha;  // [kStageChunks][kLanes]
    std::vector<int64_t> stage_chunk;   // [kStageChunks]
};

template <typename Ops, typename scalar_t>
inline void forward_tile_impl(const Problem& p, const Splat<scalar_t>* splats, int64_t tile,
                              const ForwardOut<scalar_t>& out, ForwardScratch<scalar_t>& s) {
    using V = typename Ops::template V<scalar_t>;
    using D = typename Ops::D;
    using M = typename Ops::M;
    using R = Rules<scalar_t>;
    const TileRect r = tile_rect(p, tile);
    const int64_t n = r.rows() * p.row_stride;
    const int64_t C = p.channels;
    s.T.assign(n, 1.0);
    s.accum.assign(n * C, 0.0);
    s.last.assign(n, 0);
    s.done.assign(n, 0);
    s.stage_alpha.resize(kStageChunks * kLanes);
    s.stage_chunk.resize(kStageChunks);
    pixel_columns(p, r, s.px);
    Block<scalar_t>& blk = s.block;
    blk.reserve(C, p.tile_size);
    int64_t alive = r.rows() * r.width();
    const V zero = Ops::template splat<scalar_t>(0), one = Ops::template splat<scalar_t>(1);
    const V t_min = Ops::template splat<scalar_t>(R::transmittance_min);
    const int64_t begin = p.offsets[tile];
    const int64_t end = p.offsets[tile + 1];
    for (int64_t next = begin; next < end && alive > 0;) {
        blk.clear();
        for (; next < end && blk.size < kBlockEntries; ++next) {
            if (next + kPrefetchDistance < end) prefetch_entry(p, splats, next + kPrefetchDistance);
            gather_entry<Ops>(p, splats, r, next, blk);
        }
        const int64_t num_chunks = blk.num_chunks;
        for (int64_t c0 = 0; c0 < num_chunks && alive > 0; c0 += kStageChunks) {
            // Phase A: alpha of every chunk of the batch; keep those with a lane to composite.
            int64_t staged = 0;
            for (int64_t ci = c0; ci < std::min(num_chunks, c0 + kStageChunks); ++ci) {
                const Chunk<scalar_t>& ch = blk.chunks[ci];
                M m = and_not(Ops::span(ch.lo, ch.hi), Ops::load(s.done.data() + ch.row * p.row_stride + ch.start));
                if (!any(m)) continue;  // all its pixels have stopped
                const ChunkEval<Ops, scalar_t> ev = evaluate_chunk<Ops>(blk, ch, s.px.data(), m);
                Ops::store(s.stage_alpha.data() + staged * kLanes, ev.alpha);
                s.stage_chunk[staged] = ci;
                staged += any(m);
            }
            // Phase B: composite them in order (front to back for every pixel).
            for (int64_t st = 0; st < staged && alive > 0; ++st) {
                const Chunk<scalar_t>& ch = blk.chunks[s.stage_chunk[st]];
                const int64_t q = ch.row * p.row_stride + ch.start;
                V alpha = Ops::load(static_cast<const scalar_t*>(s.stage_alpha.data() + st * kLanes));
                // Pixels may have stopped since phase A (at an earlier chunk of this batch).
                M m = and_not(gt(alpha, zero), Ops::load(s.done.data() + q));
                alpha = masked(m, alpha);
                const D T = Ops::load(s.T.data() + q);
                D next_T = T * widen(one - alpha);
                const M stop = m & le(Ops::template narrow<scalar_t>(next_T), t_min);
                if (any(stop)) {  // these pixels end before this Gaussian
                    Ops::store(s.done.data() + q, Ops::load(s.done.data() + q) | stop);
                    alive -= count(stop);
                    m = and_not(m, stop);
                    alpha = masked(m, alpha);
                    next_T = T * widen(one - alpha);
                }
                const D w = widen(alpha * Ops::template narrow<scalar_t>(T));
                const scalar_t* f = blk.feature.data() + ch.entry * C;
                for (int64_t j = 0; j < C; ++j) {
                    double* acc = s.accum.data() + j * n + q;
                    Ops::store(acc, Ops::load(acc) + Ops::splat(static_cast<double>(f[j])) * w);
                }
                Ops::store(s.T.data() + q, next_T);
                const M position = Ops::splat(static_cast<int32_t>(blk.k[ch.entry] - begin + 1));
                Ops::store(s.last.data() + q, select(m, position, Ops::load(s.last.data() + q)));
            }
        }
    }
    for (int64_t i = r.y0; i < r.y1; ++i) {
        for (int64_t j = r.x0; j < r.x1; ++j) {
            const int64_t q = (i - r.y0) * p.row_stride + (j - r.x0);
            const int64_t pix = i * p.width + j;
            for (int64_t ch = 0; ch < C; ++ch) out.image[pix * C + ch] = static_cast<scalar_t>(s.accum[ch * n + q]);
            out.alpha[pix] = static_cast<scalar_t>(1.0 - s.T[q]);
            out.transmittance[pix] = s.T[q];
            out.last[pix] = s.last[q];
        }
    }
}

// ---- Backward --------------------------------------------------------------------------------

template <typename scalar_t>
struct BackwardIn {
    const double* transmittance; // [H, W]
    const int32_t* last;         // [H, W]
    const scalar_t* grad_image;  // [H, W, C]
    const scalar_t* grad_alpha;  // [H, W]
};

template <typename scalar_t>
struct BackwardScratch {  // tile-local, row stride Problem::row_stride
    std::vector<double> T;            // transmittance behind the current Gaussian
    std::vector<double> behind;       // S: sum over Gaussians behind of w <g_image, f>
    std::vector<double> g_alpha_T;    // g_alpha_out * T_final
    std::vector<scalar_t> g_image;    // [C][pixels]
    std::vector<int32_t> last;
    std::vector<scalar_t> g_feature;  // [C][kLanes] per-lane sums of the current Gaussian
    std::vector<scalar_t> px;
    Block<scalar_t> block;
    // Phase A results per staged chunk: alpha (0 off the lanes), vis (0 where the clamp holds or
    // off the lanes), dx.
    std::vector<scalar_t> stage_alpha, stage_vis, stage_dx;
    std::vector<int64_t> stage_chunk;
};

// Slot layout per intersection: [means2d x, y | conic a, b, c | opacity | features 0..C-1].
constexpr int64_t kSlotFixed = 6;

// Per-lane sums of one Gaussian's gradients over a tile: g_o, and g_sigma times dx^2, dx dy,
// dy^2, dx, dy (the conic and mean gradients follow from those), plus g_feature (in scratch).
// They are in the scalar type: each lane sums at most a few dozen terms of one tile, and the
// lanes, then the tiles, are added in double. The per-pixel state that runs through all the
// Gaussians of a pixel (transmittance, S) stays in double.
template <typename V>
struct EntrySums {
    V o, xx, xy, yy, x, y;
};

template <typename Ops, typename scalar_t>
inline void write_slot(const Block<scalar_t>& blk, int64_t e, const EntrySums<typename Ops::template V<scalar_t>>& sum,
                       const std::vector<scalar_t>& g_feature, int64_t C, scalar_t* slot) {
    // sigma = 0.5 (a dx^2 + c dy^2) + b dx dy, dx = px - mx: d sigma / d mx = -(a dx + b dy).
    const double sx = hsum(sum.x), sy = hsum(sum.y);
    const double a = static_cast<double>(blk.a[e]), b = static_cast<double>(blk.b[e]);
    const double c = static_cast<double>(blk.c[e]);
    slot[0] = static_cast<scalar_t>(-(a * sx + b * sy));
    slot[1] = static_cast<scalar_t>(-(b * sx + c * sy));
    slot[2] = static_cast<scalar_t>(0.5 * hsum(sum.xx));
    slot[3] = static_cast<scalar_t>(hsum(sum.xy));
    slot[4] = static_cast<scalar_t>(0.5 * hsum(sum.yy));
    slot[5] = static_cast<scalar_t>(hsum(sum.o));
    for (int64_t j = 0; j < C; ++j)
        slot[kSlotFixed + j] = static_cast<scalar_t>(hsum(Ops::load(static_cast<const scalar_t*>(g_feature.data() + j * kLanes))));
}

template <typename Ops, typename scalar_t>
inline void backward_tile_impl(const Problem& p, const Splat<scalar_t>* splats, int64_t tile,
                               const BackwardIn<scalar_t>& in, scalar_t* slots, BackwardScratch<scalar_t>& s) {
    using V = typename Ops::template V<scalar_t>;
    using D = typename Ops::D;
    using M = typename Ops::M;
    const TileRect r = tile_rect(p, tile);
    const int64_t n = r.rows() * p.row_stride;
    const int64_t C = p.channels;
    const int64_t stride = kSlotFixed + C;
    const int64_t begin = p.offsets[tile];
    const int64_t end = p.offsets[tile + 1];
    // Every slot of the tile is written: zero unless its Gaussian reaches a pixel.
    std::fill(slots + begin * stride, slots + end * stride, scalar_t(0));
    s.T.assign(n, 1.0);
    s.behind.assign(n, 0.0);
    s.g_alpha_T.assign(n, 0.0);
    s.g_image.assign(n * C, scalar_t(0));
    s.last.assign(n, 0);
    s.g_feature.resize(C * kLanes);
    for (auto* v : {&s.stage_alpha, &s.stage_vis, &s.stage_dx}) v->resize(kStageChunks * kLanes);
    s.stage_chunk.resize(kStageChunks);
    pixel_columns(p, r, s.px);
    Block<scalar_t>& blk = s.block;
    blk.reserve(C, p.tile_size);
    int32_t max_last = 0;
    for (int64_t i = r.y0; i < r.y1; ++i) {
        for (int64_t j = r.x0; j < r.x1; ++j) {
            const int64_t q = (i - r.y0) * p.row_stride + (j - r.x0);
            const int64_t pix = i * p.width + j;
            s.T[q] = in.transmittance[pix];
            s.last[q] = in.last[pix];
            // d (1 - T_final) / d alpha_i = T_final / (1 - alpha_i): the part of the alpha
            // gradient that does not depend on the Gaussians behind.
            s.g_alpha_T[q] = static_cast<double>(in.grad_alpha[pix]) * in.transmittance[pix];
            for (int64_t ch = 0; ch < C; ++ch) s.g_image[ch * n + q] = in.grad_image[pix * C + ch];
            max_last = std::max(max_last, s.last[q]);
        }
    }
    const V one = Ops::template splat<scalar_t>(1), zero = Ops::template splat<scalar_t>(0);
    const D one_d = Ops::splat(1.0);
    const EntrySums<V> no_sums{zero, zero, zero, zero, zero, zero};
    for (int64_t next = begin + max_last - 1; next >= begin;) {
        blk.clear();
        for (; next >= begin && blk.size < kBlockEntries; --next) {
            if (next - kPrefetchDistance >= begin) prefetch_entry(p, splats, next - kPrefetchDistance);
            gather_entry<Ops>(p, splats, r, next, blk);
        }
        const int64_t num_chunks = blk.num_chunks;
        // The entry being summed (its chunks are consecutive) and its sums.
        int64_t entry = -1;
        EntrySums<V> sum = no_sums;
        bool touched = false;
        auto flush = [&]() {
            if (touched) write_slot<Ops>(blk, entry, sum, s.g_feature, C, slots + blk.k[entry] * stride);
        };
        for (int64_t c0 = 0; c0 < num_chunks; c0 += kStageChunks) {
            // Phase A: alpha, vis and dx of every chunk of the batch; keep those with a lane.
            int64_t staged = 0;
            for (int64_t ci = c0; ci < std::min(num_chunks, c0 + kStageChunks); ++ci) {
                const Chunk<scalar_t>& ch = blk.chunks[ci];
                const M position = Ops::splat(static_cast<int32_t>(blk.k[ch.entry] - begin));
                // Lanes in front of their pixel's last contributor.
                M m = Ops::span(ch.lo, ch.hi) & lt(position, Ops::load(s.last.data() + ch.row * p.row_stride + ch.start));
                if (!any(m)) continue;  // behind the last contributor of all its pixels
                const ChunkEval<Ops, scalar_t> ev = evaluate_chunk<Ops>(blk, ch, s.px.data(), m);
                Ops::store(s.stage_alpha.data() + staged * kLanes, ev.alpha);
                Ops::store(s.stage_vis.data() + staged * kLanes, masked(m & ev.unclamped, ev.vis));
                Ops::store(s.stage_dx.data() + staged * kLanes, ev.dx);
                s.stage_chunk[staged] = ci;
                staged += any(m);
            }
            // Phase B: back to front through the per-pixel state, summing per entry.
            for (int64_t st = 0; st < staged; ++st) {
                const Chunk<scalar_t>& ch = blk.chunks[s.stage_chunk[st]];
                if (ch.entry != entry) {
                    flush();
                    entry = ch.entry;
                    sum = no_sums;
                    touched = false;
                    std::fill(s.g_feature.begin(), s.g_feature.end(), scalar_t(0));
                }
                touched = true;
                const int64_t q = ch.row * p.row_stride + ch.start;
                const V alpha = Ops::load(static_cast<const scalar_t*>(s.stage_alpha.data() + st * kLanes));
                const D inv_one_minus = one_d / widen(one - alpha);
                const D T_behind = Ops::load(s.T.data() + q);
                const D T = T_behind * inv_one_minus;  // transmittance in front of this Gaussian
                const D w = widen(alpha) * T;
                const V w_s = Ops::template narrow<scalar_t>(w);
                // d image / d alpha_i = f_i T_i - (sum_{j>i} f_j w_j) / (1 - alpha_i), dotted with
                // g_image: front * T - S / (1 - alpha_i).
                const scalar_t* f = blk.feature.data() + ch.entry * C;
                V front = zero;
                for (int64_t j = 0; j < C; ++j) {
                    const V gc = Ops::load(static_cast<const scalar_t*>(s.g_image.data() + j * n + q));
                    front = front + gc * Ops::template splat<scalar_t>(f[j]);
                    scalar_t* gf = s.g_feature.data() + j * kLanes;
                    Ops::store(gf, Ops::load(static_cast<const scalar_t*>(gf)) + w_s * gc);
                }
                const D front_d = widen(front);
                const D S = Ops::load(s.behind.data() + q);
                const D g_alpha = front_d * T + (Ops::load(s.g_alpha_T.data() + q) - S) * inv_one_minus;
                Ops::store(s.behind.data() + q, S + w * front_d);
                Ops::store(s.T.data() + q, T);
                // vis is 0 off the lanes and where alpha is clamped (no gradient to o, sigma);
                // masking the product too keeps a non-finite g_alpha there out of the sums.
                const V vis = Ops::load(static_cast<const scalar_t*>(s.stage_vis.data() + st * kLanes));
                const V g_vis = masked(gt(vis, zero), Ops::template narrow<scalar_t>(g_alpha) * vis);
                sum.o = sum.o + g_vis;  // d loss / d o
                const V g_sigma = g_vis * Ops::template splat<scalar_t>(-blk.o[ch.entry]);
                const V dx = Ops::load(static_cast<const scalar_t*>(s.stage_dx.data() + st * kLanes));
                const V dy = Ops::template splat<scalar_t>(ch.dy);
                const V t = g_sigma * dx, u = g_sigma * dy;
                sum.x = sum.x + t;
                sum.xx = sum.xx + t * dx;
                sum.xy = sum.xy + t * dy;
                sum.y = sum.y + u;
                sum.yy = sum.yy + u * dy;
            }
        }
        flush();
    }
}

// ---- Per-ISA instantiations of the tile passes -------------------------------------------------

template <typename scalar_t>
using ForwardTileFn = void (*)(const Problem&, const Splat<scalar_t>*, int64_t, const ForwardOut<scalar_t>&,
                               ForwardScratch<scalar_t>&);
template <typename scalar_t>
using BackwardTileFn = void (*)(const Problem&, const Splat<scalar_t>*, int64_t, const BackwardIn<scalar_t>&,
                                scalar_t*, BackwardScratch<scalar_t>&);

template <typename scalar_t>
void forward_tile_portable(const Problem& p, const Splat<scalar_t>* splats, int64_t tile,
                           const ForwardOut<scalar_t>& out, ForwardScratch<scalar_t>& s) {
    forward_tile_impl<portable::Ops, scalar_t>(p, splats, tile, out, s);
}
template <typename scalar_t>
void backward_tile_portable(const Problem& p, const Splat<scalar_t>* splats, int64_t tile,
                            const BackwardIn<scalar_t>& in, scalar_t* slots, BackwardScratch<scalar_t>& s) {
    backward_tile_impl<portable::Ops, scalar_t>(p, splats, tile, in, slots, s);
}

#if RK_HAVE_AVX2
__attribute__((target("avx2"), flatten)) void forward_tile_avx2(const Problem& p, const Splat<float>* splats, int64_t tile,
                                                       const ForwardOut<float>& out, ForwardScratch<float>& s) {
    forward_tile_impl<avx2::Ops, float>(p, splats, tile, out, s);
}
__attribute__((target("avx2"), flatten)) void backward_tile_avx2(const Problem& p, const Splat<float>* splats, int64_t tile,
                                                        const BackwardIn<float>& in, float* slots,
                                                        BackwardScratch<float>& s) {
    backward_tile_impl<avx2::Ops, float>(p, splats, tile, in, slots, s);
}
#endif

// Resolves the `isa` argument: kIsaAuto picks AVX2 where the CPU has it (float32 only; float64
// always runs the portable variant). Returns false for a variant this CPU cannot run.
template <typename scalar_t>
bool pick_tile_passes(int64_t isa, ForwardTileFn<scalar_t>& forward, BackwardTileFn<scalar_t>& backward) {
    forward = forward_tile_portable<scalar_t>;
    backward = backward_tile_portable<scalar_t>;
    if (isa == kIsaPortable) return true;
    const bool avx2 = avx2_supported();
    if (isa == kIsaAvx2 && !avx2) return false;
    if (isa != kIsaAuto && isa != kIsaAvx2) return false;
#if RK_HAVE_AVX2
    if constexpr (std::is_same<scalar_t, float>::value) {
        if (avx2) {
            forward = forward_tile_avx2;
            backward = backward_tile_avx2;
        }
    }
#endif
    return true;
}

// ---- Reusable buffers -------------------------------------------------------------------------
//
// The per-call arrays of megabytes (Gaussian parameters, gradient slots, reduction sums) come
// from a small process-wide pool and go back to it after the call. Freshly allocated, they would
// be returned to the operating system on every free and page-faulted in again on every call,
// which costs about as much as a tenth of the compositing itself.
class BufferPool {
  public:
    static BufferPool& instance() {
        static BufferPool pool;
        return pool;
    }
    std::unique_ptr<std::vector<unsigned char>> acquire(size_t bytes) {
        std::unique_ptr<std::vector<unsigned char>> buffer;
        {
            std::lock_guard<std::mutex> lock(mutex_);
            if (!free_.empty()) {  // the largest one, so that buffers do not all grow
                auto largest = std::max_element(free_.begin(), free_.end(),
                                                [](const auto& x, const auto& y) { return x->size() < y->size(); });
                buffer = std::move(*largest);
                free_.erase(largest);
            }
        }
        if (!buffer) buffer.reset(new std::vector<unsigned char>());
        if (buffer->size() < bytes) buffer->resize(bytes);
        return buffer;
    }
    void release(std::unique_ptr<std::vector<unsigned char>> buffer) {
        std::lock_guard<std::mutex> lock(mutex_);
        if (free_.size() < kMaxFree) free_.push_back(std::move(buffer));
    }

  private:
    static constexpr size_t kMaxFree = 16;
    std::mutex mutex_;
    std::vector<std::unique_ptr<std::vector<unsigned char>>> free_;
};

// An uninitialised array of n trivially copyable T from the pool, returned to it on destruction.
template <typename T>
class PooledArray {
    static_assert(std::is_trivially_copyable<T>::value, "pooled arrays hold plain data");

  public:
    explicit PooledArray(size_t n) : buffer_(BufferPool::instance().acquire(n * sizeof(T))) {}
    ~PooledArray() { BufferPool::instance().release(std::move(buffer_)); }
    PooledArray(const PooledArray&) = delete;
    PooledArray& operator=(const PooledArray&) = delete;
    T* data() { return reinterpret_cast<T*>(buffer_->data()); }
    const T* data() const { return reinterpret_cast<const T*>(buffer_->data()); }

  private:
    std::unique_ptr<std::vector<unsigned char>> buffer_;
};

// ---- Reduction of the backward slots -----------------------------------------------------------

template <typename scalar_t>
struct Gradients {
    scalar_t* means2d;   // [N, 2]
    scalar_t* conics;    // [N, 3]
    scalar_t* opacities; // [N]
    scalar_t* features;  // [N, C]
};

// Sums the slots of every Gaussian in increasing intersection order. Gaussians are split into
// contiguous blocks, one per work item; each item scans all intersections and keeps its own, so
// the order of every sum is fixed regardless of the number of threads.
template <typename scalar_t>
void reduce_slots(const Problem& p, const scalar_t* slots, int64_t threads, const Gradients<scalar_t>& out) {
    const int64_t N = p.num_gaussians;
    const int64_t C = p.channels;
    const int64_t stride = kSlotFixed + C;
    const int64_t M = p.offsets[p.tiles_x * p.tiles_y];
    const int64_t blocks = std::max<int64_t>(1, std::min<int64_t>(threads, N));
    const int64_t per_block = (N + blocks - 1) / blocks;
    parallel_items(blocks, threads, [&](int64_t block, int64_t) {
        const int64_t lo = block * per_block;
        const int64_t hi = std::min(N, lo + per_block);
        if (lo >= hi) return;
        PooledArray<double> pooled(static_cast<size_t>((hi - lo) * stride));
        double* sums = pooled.data();
        std::fill(sums, sums + (hi - lo) * stride, 0.0);
        for (int64_t k = 0; k < M; ++k) {
            const int64_t g = p.gaussian_ids[k];
            if (g < lo || g >= hi) continue;
            double* dst = &sums[(g - lo) * stride];
            const scalar_t* src = slots + k * stride;
            for (int64_t v = 0; v < stride; ++v) dst[v] += static_cast<double>(src[v]);
        }
        for (int64_t g = lo; g < hi; ++g) {
            const double* src = &sums[(g - lo) * stride];
            out.means2d[2 * g] = static_cast<scalar_t>(src[0]);
            out.means2d[2 * g + 1] = static_cast<scalar_t>(src[1]);
            out.conics[3 * g] = static_cast<scalar_t>(src[2]);
            out.conics[3 * g + 1] = static_cast<scalar_t>(src[3]);
            out.conics[3 * g + 2] = static_cast<scalar_t>(src[4]);
            out.opacities[g] = static_cast<scalar_t>(src[5]);
            for (int64_t ch = 0; ch < C; ++ch) out.features[g * C + ch] = static_cast<scalar_t>(src[kSlotFixed + ch]);
        }
    });
}

// ---- Tile binning (same lists as tiles.bin_gaussians, without a global sort of intersections) ----
//
// A visible Gaussian is listed in every tile its box [m - r, m + r] touches, with the tile range
// computed exactly as tiles.tile_ranges does (float64 floor/ceil of (m -/+ r) / tile_size, clamped
// to the grid). Lists are filled by walking the visible Gaussians in a stable depth order, so each
// tile's list is front to back with ties by Gaussian index: a radix sort by depth, then a
// counting sort into the tiles, O(N + M).

struct BinProblem {
    const int32_t* radii;     // [N, 2]
    const uint8_t* visible;   // [N]
    int64_t num_gaussians;
    int64_t tile_size, tiles_x, tiles_y;
};

struct TileSpan {
    int64_t x0, x1, y0, y1;  // tiles [x0, x1) x [y0, y1)
};

inline int64_t clamp_tile(double v, int64_t hi) {
    return static_cast<int64_t>(std::min<double>(static_cast<double>(hi), std::max(0.0, v)));
}

template <typename scalar_t>
bool tile_span(const BinProblem& b, const scalar_t* means2d, int64_t g, TileSpan& s) {
    if (!b.visible[g]) return false;
    const double mx = static_cast<double>(means2d[2 * g]);
    const double my = static_cast<double>(means2d[2 * g + 1]);
    if (!std::isfinite(mx) || !std::isfinite(my)) return false;
    const double rx = static_cast<double>(b.radii[2 * g]);
    const double ry = static_cast<double>(b.radii[2 * g + 1]);
    const double ts = static_cast<double>(b.tile_size);
    s.x0 = clamp_tile(std::floor((mx - rx) / ts), b.tiles_x);
    s.x1 = clamp_tile(std::ceil((mx + rx) / ts), b.tiles_x);
    s.y0 = clamp_tile(std::floor((my - ry) / ts), b.tiles_y);
    s.y1 = clamp_tile(std::ceil((my + ry) / ts), b.tiles_y);
    return s.x1 > s.x0 && s.y1 > s.y0;
}

template <typename scalar_t>
int64_t bin_count(const BinProblem& b, const scalar_t* means2d, int64_t* offsets) {
    const int64_t tiles = b.tiles_x * b.tiles_y;
    std::fill(offsets, offsets + tiles + 1, int64_t(0));
    TileSpan s;
    for (int64_t g = 0; g < b.num_gaussians; ++g) {
        if (!tile_span(b, means2d, g, s)) continue;
        for (int64_t ty = s.y0; ty < s.y1; ++ty)
            for (int64_t tx = s.x0; tx < s.x1; ++tx) ++offsets[ty * b.tiles_x + tx + 1];
    }
    for (int64_t t = 0; t < tiles; ++t) offsets[t + 1] += offsets[t];
    return offsets[tiles];
}

// An unsigned integer whose order is the order of the (non-NaN) value; -0 and +0 map alike, as
// they compare equal.
template <typename scalar_t>
using SortKey = typename std::conditional<sizeof(scalar_t) == 4, uint32_t, uint64_t>::type;

template <typename scalar_t>
SortKey<scalar_t> sort_key(scalar_t v) {
    using K = SortKey<scalar_t>;
    v = v + scalar_t(0);  // -0 -> +0
    K bits;
    std::memcpy(&bits, &v, sizeof bits);
    const K sign = K(1) << (8 * sizeof(K) - 1);
    return (bits & sign) ? ~bits : (bits | sign);
}

// Stable sort of `order` (Gaussian indices) by depth: an LSD radix sort on sort_key, 8 bits per
// pass, so ties keep their (increasing index) order exactly as torch.sort(stable=True) does.
template <typename scalar_t>
void sort_by_depth(std::vector<int64_t>& order, const scalar_t* depths) {
    using K = SortKey<scalar_t>;
    const size_t n = order.size();
    std::vector<K> keys(n), keys_tmp(n);
    std::vector<int64_t> order_tmp(n);
    for (size_t i = 0; i < n; ++i) keys[i] = sort_key(depths[order[i]]);
    for (unsigned shift = 0; shift < 8 * sizeof(K); shift += 8) {
        size_t count[257] = {0};
        for (size_t i = 0; i < n; ++i) ++count[((keys[i] >> shift) & 0xFF) + 1];
        if (std::find(count + 1, count + 257, n) != count + 257) continue;  // one digit value: order kept
        for (int d = 0; d < 256; ++d) count[d + 1] += count[d];
        for (size_t i = 0; i < n; ++i) {
            const size_t dst = count[(keys[i] >> shift) & 0xFF]++;
            keys_tmp[dst] = keys[i];
            order_tmp[dst] = order[i];
        }
        keys.swap(keys_tmp);
        order.swap(order_tmp);
    }
}

template <typename scalar_t>
void bin_fill(const BinProblem& b, const scalar_t* means2d, const scalar_t* depths, const int64_t* offsets,
              int64_t* ids) {
    std::vector<int64_t> order;
    order.reserve(static_cast<size_t>(b.num_gaussians));
    TileSpan s;
    for (int64_t g = 0; g < b.num_gaussians; ++g)
        if (tile_span(b, means2d, g, s)) order.push_back(g);
    sort_by_depth(order, depths);
    std::vector<int64_t> cursor(offsets, offsets + b.tiles_x * b.tiles_y);
    for (int64_t g : order) {
        tile_span(b, means2d, g, s);
        for (int64_t ty = s.y0; ty < s.y1; ++ty)
            for (int64_t tx = s.x0; tx < s.x1; ++tx) ids[cursor[ty * b.tiles_x + tx]++] = g;
    }
}

BinProblem make_bin_problem(const int32_t* radii, const uint8_t* visible, int64_t n, int64_t width, int64_t height,
                            int64_t tile_size) {
    BinProblem b;
    b.radii = radii;
    b.visible = visible;
    b.num_gaussians = n;
    b.tile_size = tile_size;
    b.tiles_x = (width + tile_size - 1) / tile_size;
    b.tiles_y = (height + tile_size - 1) / tile_size;
    return b;
}

Problem make_problem(const void* means2d, const void* conics, const void* opacities, const void* features,
                     const int32_t* radii, int64_t n, int64_t c, const int64_t* offsets, const int64_t* ids,
                     int64_t width, int64_t height, int64_t tile_size) {
    Problem p;
    p.means2d = means2d;
    p.conics = conics;
    p.opacities = opacities;
    p.features = features;
    p.radii = radii;
    p.num_gaussians = n;
    p.channels = c;
    p.offsets = offsets;
    p.gaussian_ids = ids;
    p.width = width;
    p.height = height;
    p.tile_size = tile_size;
    p.tiles_x = (width + tile_size - 1) / tile_size;
    p.tiles_y = (height + tile_size - 1) / tile_size;
    p.row_stride = (tile_size + kLanes - 1) / kLanes * kLanes;
    return p;
}

// Splat parameters of every Gaussian, computed in parallel blocks (each entry written once).
template <typename scalar_t>
void prepare_splats(const Problem& p, int64_t threads, Splat<scalar_t>* splats) {
    const int64_t block = 4096;
    parallel_items((p.num_gaussians + block - 1) / block, threads, [&](int64_t b, int64_t) {
        const int64_t end = std::min(p.num_gaussians, (b + 1) * block);
        for (int64_t g = b * block; g < end; ++g) splats[g] = prepare_splat<scalar_t>(p, g);
    });
}

// Status codes of the entry points.
constexpr int kOk = 0;
constexpr int kOutOfMemory = 2;
constexpr int kFailed = 3;
constexpr int kIsaUnavailable = 4;

template <typename scalar_t>
int forward(const Problem& p, int64_t threads, int64_t isa, const ForwardOut<scalar_t>& out) {
    ForwardTileFn<scalar_t> forward_tile;
    BackwardTileFn<scalar_t> unused;
    if (!pick_tile_passes<scalar_t>(isa, forward_tile, unused)) return kIsaUnavailable;
    const int64_t workers = std::max<int64_t>(1, threads);
    PooledArray<Splat<scalar_t>> splats(static_cast<size_t>(p.num_gaussians));
    prepare_splats<scalar_t>(p, workers, splats.data());
    std::vector<ForwardScratch<scalar_t>> scratch(static_cast<size_t>(workers));
    parallel_items(p.tiles_x * p.tiles_y, workers,
                   [&](int64_t tile, int64_t w) { forward_tile(p, splats.data(), tile, out, scratch[w]); });
    return kOk;
}

template <typename scalar_t>
int backward(const Problem& p, int64_t threads, int64_t isa, const BackwardIn<scalar_t>& in,
             const Gradients<scalar_t>& out) {
    ForwardTileFn<scalar_t> unused;
    BackwardTileFn<scalar_t> backward_tile;
    if (!pick_tile_passes<scalar_t>(isa, unused, backward_tile)) return kIsaUnavailable;
    const int64_t workers = std::max<int64_t>(1, threads);
    const int64_t M = p.offsets[p.tiles_x * p.tiles_y];
    // Every slot is written by its tile (zeros where the Gaussian contributes nothing).
    PooledArray<scalar_t> slots(static_cast<size_t>(M * (kSlotFixed + p.channels)));
    PooledArray<Splat<scalar_t>> splats(static_cast<size_t>(p.num_gaussians));
    prepare_splats<scalar_t>(p, workers, splats.data());
    std::vector<BackwardScratch<scalar_t>> scratch(static_cast<size_t>(workers));
    parallel_items(p.tiles_x * p.tiles_y, workers, [&](int64_t tile, int64_t w) {
        backward_tile(p, splats.data(), tile, in, slots.data(), scratch[w]);
    });
    reduce_slots<scalar_t>(p, slots.data(), workers, out);
    return kOk;
}

// C entry points return 0 on success and a non-zero code on failure (no exception may cross).
template <typename F>
int guarded(F&& f) {
    try {
        return f();
    } catch (const std::bad_alloc&) {
        return kOutOfMemory;
    } catch (...) {
        return kFailed;
    }
}

}  // namespace

#define RK_ENTRY_POINTS(SUFFIX, SCALAR)                                                                         \
    extern "C" int rk_forward_##SUFFIX(const SCALAR* means2d, const SCALAR* conics, const SCALAR* opacities,    \
                                       const SCALAR* features, const int32_t* radii, int64_t n, int64_t c,      \
                                       const int64_t* offsets, const int64_t* ids, int64_t width,               \
                                       int64_t height, int64_t tile_size, int64_t threads, int64_t isa,         \
                                       SCALAR* image, SCALAR* alpha, double* transmittance, int32_t* last) {    \
        return guarded([&] {                                                                                    \
            const Problem p = make_problem(means2d, conics, opacities, features, radii, n, c, offsets, ids,      \
                                           width, height, tile_size);                                           \
            return forward<SCALAR>(p, threads, isa, ForwardOut<SCALAR>{image, alpha, transmittance, last});     \
        });                                                                                                     \
    }                                                                                                           \
    extern "C" int rk_backward_##SUFFIX(const SCALAR* means2d, const SCALAR* conics, const SCALAR* opacities,   \
                                        const SCALAR* features, const int32_t* radii, int64_t n, int64_t c,     \
                                        const int64_t* offsets, const int64_t* ids, int64_t width,              \
                                        int64_t height, int64_t tile_size, int64_t threads, int64_t isa,        \
                                        const double* transmittance, const int32_t* last,                       \
                                        const SCALAR* grad_image, const SCALAR* grad_alpha,                     \
                                        SCALAR* grad_means2d, SCALAR* grad_conics, SCALAR* grad_opacities,      \
                                        SCALAR* grad_features) {                                                \
        return guarded([&] {                                                                                    \
            const Problem p = make_problem(means2d, conics, opacities, features, radii, n, c, offsets, ids,      \
                                           width, height, tile_size);                                           \
            return backward<SCALAR>(p, threads, isa,                                                            \
                                    BackwardIn<SCALAR>{transmittance, last, grad_image, grad_alpha},            \
                                    Gradients<SCALAR>{grad_means2d, grad_conics, grad_opacities, grad_features}); \
        });                                                                                                     \
    }

#define RK_BIN_ENTRY_POINTS(SUFFIX, SCALAR)                                                                     \
    extern "C" int64_t rk_bin_count_##SUFFIX(const SCALAR* means2d, const int32_t* radii, const uint8_t* visible,  \
                                             int64_t n, int64_t width, int64_t height, int64_t tile_size,         \
                                             int64_t* offsets) {                                                  \
        try {                                                                                                     \
            return bin_count(make_bin_problem(radii, visible, n, width, height, tile_size), means2d, offsets);     \
        } catch (...) {                                                                                           \
            return -1;                                                                                            \
        }                                                                                                         \
    }                                                                                                             \
    extern "C" int rk_bin_fill_##SUFFIX(const SCALAR* means2d, const int32_t* radii, const uint8_t* visible,       \
                                        const SCALAR* depths, int64_t n, int64_t width, int64_t height,           \
                                        int64_t tile_size, const int64_t* offsets, int64_t* ids) {                \
        return guarded([&] {                                                                                      \
            bin_fill(make_bin_problem(radii, visible, n, width, height, tile_size), means2d, depths, offsets, ids); \
            return 0;                                                                                             \
        });                                                                                                       \
    }

RK_BIN_ENTRY_POINTS(f32, float)
RK_BIN_ENTRY_POINTS(f64, double)
RK_ENTRY_POINTS(f32, float)
RK_ENTRY_POINTS(f64, double)

extern "C" int rk_abi_version() { return kAbiVersion; }

// 1 when this CPU can run the given variant (kIsaPortable, kIsaAvx2), else 0.
extern "C" int rk_isa_supported(int64_t isa) {
    if (isa == kIsaPortable) return 1;
    if (isa == kIsaAvx2) return avx2_supported() ? 1 : 0;
    return 0;
}

// o exp(-sigma) for float32 as the compositor computes it (fast exp, the C library's expf near
// the alpha thresholds) with a given variant, and the C library's expf: test hooks for the exp.
namespace {
template <typename Ops>
inline void raw_alpha_chunk(const float* sigma, const float* o, float* out) {
    typename Ops::template V<float> vis;
    Ops::store(out, alpha_raw<Ops, float>(Ops::load(sigma), Ops::load(o), Ops::span(0, kLanes - 1), vis));
}
#if RK_HAVE_AVX2
__attribute__((target("avx2"), flatten)) void raw_alpha_chunk_avx2(const float* sigma, const float* o, float* out) {
    raw_alpha_chunk<avx2::Ops>(sigma, o, out);
}
#endif
}  // namespace

extern "C" int rk_raw_alpha_f32(const float* sigma, const float* opacity, float* out, int64_t n, int64_t isa) {
    if (isa != kIsaPortable && !(isa == kIsaAvx2 && avx2_supported())) return kIsaUnavailable;
    for (int64_t i = 0; i < n; i += kLanes) {
        float s[kLanes] = {0}, o[kLanes] = {0}, r[kLanes];
        const int64_t m = std::min<int64_t>(kLanes, n - i);
        std::copy(sigma + i, sigma + i + m, s);
        std::copy(opacity + i, opacity + i + m, o);
#if RK_HAVE_AVX2
        if (isa == kIsaAvx2)
            raw_alpha_chunk_avx2(s, o, r);
        else
#endif
            raw_alpha_chunk<portable::Ops>(s, o, r);
        std::copy(r, r + m, out + i);
    }
    return kOk;
}

extern "C" void rk_libm_expf(const float* x, float* out, int64_t n) {
    for (int64_t i = 0; i < n; ++i) out[i] = std::exp(x[i]);
}
