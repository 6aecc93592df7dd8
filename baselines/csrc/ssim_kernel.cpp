// 3DGS's SSIM map on the CPU, channels-last: forward and hand-written backward (image gradient).
//
// Compiled on first use by baselines/ssim_kernel.py into a plain shared library (no Python or torch
// headers; baselines/native_build.py) and called through ctypes with raw pointers to contiguous
// [B, H, W, C] tensors. It computes what ssim_map_torch (baselines/metrics.py) computes, which stays
// the oracle of the tests and the fallback: per image and channel, the windowed moments
//     mu_x = w * x, mu_y = w * y, e_xx = w * x^2, e_yy = w * y^2, e_xy = w * xy
// with w the separable 11-tap Gaussian (taps passed in), zero padding of 5 pixels ('same' size), then
//     S = (2 mu_x mu_y + C1)(2 sigma_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2))
// with sigma_x^2 = e_xx - mu_x^2, sigma_y^2 = e_yy - mu_y^2, sigma_xy = e_xy - mu_x mu_y.
//
// Backward (x only; y is a constant target): with N1, N2, D1, D2 the four factors of S,
//     dS/dmu_x = 2 (mu_y N2 - S mu_x D2) / (D1 D2),  dS/dsigma_x^2 = -S / D2,  dS/dsigma_xy = 2 N1 / (D1 D2),
// and since d mu_x(q)/dx(p) = w(q-p), d sigma_x^2(q)/dx(p) = w(q-p) (2 x(p) - 2 mu_x(q)),
// d sigma_xy(q)/dx(p) = w(q-p) (y(p) - mu_y(q)), the gradient is three windowed sums (the window is
// symmetric, so correlation = convolution) of per-pixel partials, combined per pixel:
//     dL/dx(p) = (w * (G P_a))(p) + x(p) (w * (G P_b))(p) + y(p) (w * (G P_c))(p),
//     P_a = dS/dmu_x - 2 mu_x dS/dsigma_x^2 - mu_y dS/dsigma_xy,  P_b = 2 dS/dsigma_x^2,  P_c = dS/dsigma_xy,
// G = dL/dS. The forward stores P_a, P_b, P_c when asked (training), so the backward is one
// three-channel separable filtering.
//
// Layout: a row of an image is W * C contiguous values; the horizontal pass filters it with taps
// C apart (every channel at once), the vertical pass sums 11 horizontally filtered rows kept in a
// ring buffer. Work units are (image, block of rows); a unit recomputes the 5 horizontal rows on
// either side of its block, so the arithmetic of every output value is the same whatever the
// blocking: results do not depend on the thread count.

#include <algorithm>
#include <cstdint>
#include <exception>
#include <functional>
#include <new>
#include <thread>
#include <vector>

namespace {

constexpr int kAbiVersion = 1;
constexpr int kOk = 0;
constexpr int kOutOfMemory = 2;
constexpr int kFailed = 3;
constexpr int kTaps = 11;
constexpr int kRadius = kTaps / 2;
constexpr int64_t kMinRowsPerUnit = 16;  // smaller blocks recompute too many halo rows

struct Shape {
    int64_t b, h, w, c;
    int64_t row() const { return w * c; }
    int64_t image() const { return h * w * c; }
};

// Separable 'same' filtering of M planes of one image over output rows [h0, h1).
//   fill(r, rows): writes row r of each of the M source planes into rows[m][0, W * C); each buffer
//                  has kRadius * C zeros on either side that stay zero (the zero padding);
//   finish(h, sums): receives the M filtered rows h (each W * C values).
template <typename T, int M, typename Fill, typename Finish>
void filter_rows(const Shape& s, const T* taps, int64_t h0, int64_t h1, Fill&& fill, Finish&& finish) {
    const int64_t n = s.row(), c = s.c, padded = n + 2 * kRadius * c;
    std::vector<T> source(static_cast<size_t>(M * padded), T(0));
    std::vector<T> ring(static_cast<size_t>(kTaps * M * n));
    std::vector<T> sums(static_cast<size_t>(M * n));
    const std::vector<T> zero(static_cast<size_t>(M * n), T(0));
    T g[kTaps];
    for (int k = 0; k < kTaps; ++k) g[k] = taps[k];
    T* rows[M];
    for (int m = 0; m < M; ++m) rows[m] = source.data() + m * padded;

    auto horizontal = [&](int64_t r) {  // filtered row r into its ring slot
        T* into[M];
        for (int m = 0; m < M; ++m) into[m] = rows[m] + kRadius * c;
        fill(r, into);
        T* slot = ring.data() + (r % kTaps) * M * n;
        for (int m = 0; m < M; ++m) {
            const T* src = rows[m];
            T* dst = slot + m * n;
            for (int64_t i = 0; i < n; ++i) {
                T acc = T(0);
                for (int k = 0; k < kTaps; ++k) acc += g[k] * src[i + k * c];
                dst[i] = acc;
            }
        }
    };

    const int64_t first = std::max<int64_t>(0, h0 - kRadius);
    for (int64_t r = first; r < std::min(s.h, h0 + kRadius); ++r) horizontal(r);
    const T* out[M];
    for (int m = 0; m < M; ++m) out[m] = sums.data() + m * n;
    for (int64_t h = h0; h < h1; ++h) {
        if (h + kRadius < s.h) horizontal(h + kRadius);
        const T* tap_rows[kTaps];  // rows outside the image read the zero row (the zero padding)
        for (int k = 0; k < kTaps; ++k) {
            const int64_t r = h + k - kRadius;
            tap_rows[k] = (r < 0 || r >= s.h) ? zero.data() : ring.data() + (r % kTaps) * M * n;
        }
        T* acc = sums.data();
        for (int64_t i = 0; i < M * n; ++i) {  // all taps in a register: one store per value
            T v = T(0);
            for (int k = 0; k < kTaps; ++k) v += g[k] * tap_rows[k][i];
            acc[i] = v;
        }
        finish(h, out);
    }
}

// Runs fn(image, h0, h1) over (image, row block) units on up to `threads` workers; the first
// exception wins. One unit per image when there are at least as many images as workers.
int parallel_units(const Shape& s, int64_t threads, const std::function<void(int64_t, int64_t, int64_t)>& fn) {
    try {
        threads = std::max<int64_t>(1, threads);
        int64_t blocks_per_image = 1;
        if (threads > s.b) {
            const int64_t wanted = (2 * threads + s.b - 1) / s.b;  // about two units per worker
            blocks_per_image = std::max<int64_t>(1, std::min(wanted, s.h / kMinRowsPerUnit));
        }
        const int64_t rows_per_block = (s.h + blocks_per_image - 1) / blocks_per_image;
        const int64_t units = s.b * blocks_per_image;
        auto run_unit = [&](int64_t u) {
            const int64_t image = u / blocks_per_image, h0 = (u % blocks_per_image) * rows_per_block;
            const int64_t h1 = std::min(s.h, h0 + rows_per_block);
            if (h0 < h1) fn(image, h0, h1);
        };
        threads = std::min(threads, units);
        if (threads <= 1) {
            for (int64_t u = 0; u < units; ++u) run_unit(u);
            return kOk;
        }
        std::vector<std::exception_ptr> errors(static_cast<size_t>(threads));
        auto worker = [&](int64_t w) {
            try {
                for (int64_t u = w; u < units; u += threads) run_unit(u);
            } catch (...) {
                errors[static_cast<size_t>(w)] = std::current_exception();
            }
        };
        std::vector<std::thread> pool;
        pool.reserve(static_cast<size_t>(threads - 1));
        for (int64_t w = 1; w < threads; ++w) pool.emplace_back(worker, w);
        worker(0);
        for (auto& th : pool) th.join();
        for (auto& e : errors)
            if (e) std::rethrow_exception(e);
        return kOk;
    } catch (const std::bad_alloc&) {
        return kOutOfMemory;
    } catch (...) {
        return kFailed;
    }
}

// SSIM map of image `b`, rows [h0, h1); partials (P_a, P_b, P_c planes of [B, H, W, C]) when not null.
template <typename T>
void forward_unit(const Shape& s, const T* x, const T* y, const T* taps, T c1, T c2, int64_t b, int64_t h0,
                  int64_t h1, T* out, T* p_a, T* p_b, T* p_c) {
    const int64_t n = s.row(), base = b * s.image();
    auto fill = [&](int64_t r, T* const* rows) {
        const T* __restrict__ xr = x + base + r * n;
        const T* __restrict__ yr = y + base + r * n;
        T* __restrict__ r0 = rows[0];
        T* __restrict__ r1 = rows[1];
        T* __restrict__ r2 = rows[2];
        T* __restrict__ r3 = rows[3];
        T* __restrict__ r4 = rows[4];
        for (int64_t i = 0; i < n; ++i) {
            const T xv = xr[i], yv = yr[i];
            r0[i] = xv;
            r1[i] = yv;
            r2[i] = xv * xv;
            r3[i] = yv * yv;
            r4[i] = xv * yv;
        }
    };
    auto finish = [&](int64_t h, const T* const* m) {
        const int64_t at = base + h * n;
        const T* __restrict__ m0 = m[0];
        const T* __restrict__ m1 = m[1];
        const T* __restrict__ m2 = m[2];
        const T* __restrict__ m3 = m[3];
        const T* __restrict__ m4 = m[4];
        T* __restrict__ o = out + at;
        if (p_a == nullptr) {  // no gradient wanted: the map alone
            for (int64_t i = 0; i < n; ++i) {
                const T mu_x = m0[i], mu_y = m1[i];
                const T mu_xx = mu_x * mu_x, mu_yy = mu_y * mu_y, mu_xy = mu_x * mu_y;
                const T var_x = m2[i] - mu_xx, var_y = m3[i] - mu_yy, cov = m4[i] - mu_xy;
                o[i] = ((T(2) * mu_xy + c1) * (T(2) * cov + c2)) / ((mu_xx + mu_yy + c1) * (var_x + var_y + c2));
            }
            return;
        }
        T* __restrict__ pa = p_a + at;
        T* __restrict__ pb = p_b + at;
        T* __restrict__ pc = p_c + at;
        for (int64_t i = 0; i < n; ++i) {
            const T mu_x = m0[i], mu_y = m1[i];
            const T mu_xx = mu_x * mu_x, mu_yy = mu_y * mu_y, mu_xy = mu_x * mu_y;
            const T var_x = m2[i] - mu_xx, var_y = m3[i] - mu_yy, cov = m4[i] - mu_xy;
            const T n1 = T(2) * mu_xy + c1, n2 = T(2) * cov + c2;
            const T d2 = var_x + var_y + c2;
            const T den = (mu_xx + mu_yy + c1) * d2;
            const T ssim = (n1 * n2) / den;
            o[i] = ssim;
            const T d_mu = T(2) * (mu_y * n2 - ssim * mu_x * d2) / den;
            const T d_var = -ssim / d2;
            const T d_cov = T(2) * n1 / den;
            pa[i] = d_mu - T(2) * mu_x * d_var - mu_y * d_cov;
            pb[i] = T(2) * d_var;
            pc[i] = d_cov;
        }
    };
    filter_rows<T, 5>(s, taps, h0, h1, fill, finish);
}

template <typename T>
void backward_unit(const Shape& s, const T* x, const T* y, const T* taps, const T* grad, const T* p_a,
                   const T* p_b, const T* p_c, int64_t b, int64_t h0, int64_t h1, T* grad_x) {
    const int64_t n = s.row(), base = b * s.image();
    auto fill = [&](int64_t r, T* const* rows) {
        const int64_t at = base + r * n;
        const T* __restrict__ g = grad + at;
        const T* __restrict__ pa = p_a + at;
        const T* __restrict__ pb = p_b + at;
        const T* __restrict__ pc = p_c + at;
        T* __restrict__ r0 = rows[0];
        T* __restrict__ r1 = rows[1];
        T* __restrict__ r2 = rows[2];
        for (int64_t i = 0; i < n; ++i) {
            r0[i] = g[i] * pa[i];
            r1[i] = g[i] * pb[i];
            r2[i] = g[i] * pc[i];
        }
    };
    auto finish = [&](int64_t h, const T* const* m) {
        const int64_t at = base + h * n;
        const T* __restrict__ m0 = m[0];
        const T* __restrict__ m1 = m[1];
        const T* __restrict__ m2 = m[2];
        const T* __restrict__ xr = x + at;
        const T* __restrict__ yr = y + at;
        T* __restrict__ gx = grad_x + at;
        for (int64_t i = 0; i < n; ++i) gx[i] = m0[i] + xr[i] * m1[i] + yr[i] * m2[i];
    };
    filter_rows<T, 3>(s, taps, h0, h1, fill, finish);
}

}  // namespace

#define SSIM_DEFINE(SUFFIX, SCALAR)                                                                                \
    extern "C" int ssim_forward_##SUFFIX(const SCALAR* x, const SCALAR* y, const SCALAR* taps, int64_t b,        \
                                         int64_t h, int64_t w, int64_t c, double c1, double c2, int64_t threads,  \
                                         SCALAR* out, SCALAR* p_a, SCALAR* p_b, SCALAR* p_c) {                    \
        const Shape s{b, h, w, c};                                                                                 \
        return parallel_units(s, threads, [&](int64_t image, int64_t h0, int64_t h1) {                             \
            forward_unit<SCALAR>(s, x, y, taps, static_cast<SCALAR>(c1), static_cast<SCALAR>(c2), image, h0, h1, \
                                 out, p_a, p_b, p_c);                                                              \
        });                                                                                                        \
    }                                                                                                              \
    extern "C" int ssim_backward_##SUFFIX(const SCALAR* x, const SCALAR* y, const SCALAR* taps, int64_t b,       \
                                          int64_t h, int64_t w, int64_t c, int64_t threads, const SCALAR* grad,  \
                                          const SCALAR* p_a, const SCALAR* p_b, const SCALAR* p_c,                \
                                          SCALAR* grad_x) {                                                        \
        const Shape s{b, h, w, c};                                                                                 \
        return parallel_units(s, threads, [&](int64_t image, int64_t h0, int64_t h1) {                             \
            backward_unit<SCALAR>(s, x, y, taps, grad, p_a, p_b, p_c, image, h0, h1, grad_x);                     \
        });                                                                                                        \
    }

SSIM_DEFINE(f32, float)
SSIM_DEFINE(f64, double)

extern "C" int ssim_abi_version() { return kAbiVersion; }
