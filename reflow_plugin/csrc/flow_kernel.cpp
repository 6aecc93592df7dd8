// ReFlow's per-Gaussian flow channels on the CPU: forward and hand-written backward.
//
// Compiled on first use by reflow_plugin/flow_kernel.py into a plain shared library (no Python or
// torch headers; baselines/native_build.py) and called through ctypes with raw pointers to
// contiguous tensors. It computes what flow_features_torch (reflow_plugin/flow.py) computes, which
// stays the oracle of the tests and the fallback, with the same rules in the same order:
//     valid = both views in front of the near plane with finite means / covariances, a finite conic
//             in a, screen footprints and centres plausible in both (MAX_FOOTPRINT_PX, MAX_SCREEN_PX);
//     A = sqrt(S_b) sqrt(S_a^-1) (symmetric 2x2 roots, trace-scaled, clamps as sqrtm_spd2);
//     c = m_b - A m_a; channels (A00, A01, A10, A11, c_x, c_y, 1); invalid rows (1, 0, 0, 1, 0, 0, 0).
// Backward: gradients of means2d_a, conics_a, means2d_b and cov2d_b (only its [0,0], [0,1] and
// [1,1] entries enter, as in the twin); clamps pass the gradient where their input >= the bound,
// as torch's clamp_min does. Rows are independent: blocks of rows over std::threads, results do
// not depend on the thread count.

#include <algorithm>
#include <cmath>
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
constexpr int64_t kBlockRows = 4096;

struct Limits {
    double near_plane, max_trace, max_screen;
};

template <typename T>
bool all_finite(const T* v, int count) {
    for (int k = 0; k < count; ++k)
        if (!std::isfinite(v[k])) return false;
    return true;
}

template <typename T>
bool row_valid(int64_t i, const T* ma, const T* cov_a, const T* conic_a, const T* depth_a, const T* mb,
               const T* cov_b, const T* depth_b, const Limits& lim) {
    const T near_plane = static_cast<T>(lim.near_plane);
    const T max_trace = static_cast<T>(lim.max_trace);
    const T max_screen = static_cast<T>(lim.max_screen);
    const T* m_a = ma + 2 * i;
    const T* m_b = mb + 2 * i;
    const T* s_a = cov_a + 4 * i;
    const T* s_b = cov_b + 4 * i;
    const bool in_b = depth_b[i] >= near_plane && all_finite(m_b, 2) && all_finite(s_b, 4);
    const bool in_a = depth_a[i] >= near_plane && all_finite(m_a, 2) && all_finite(s_a, 4);
    const bool plausible_a = (s_a[0] + s_a[3]) <= max_trace && std::abs(m_a[0]) <= max_screen &&
                             std::abs(m_a[1]) <= max_screen;
    const bool plausible_b = (s_b[0] + s_b[3]) <= max_trace && std::abs(m_b[0]) <= max_screen &&
                             std::abs(m_b[1]) <= max_screen;
    return in_b && in_a && plausible_a && plausible_b && all_finite(conic_a + 3 * i, 3);
}

// sqrtm_spd2's intermediate values for one symmetric 2x2 matrix [[a, b], [b, c]].
template <typename T>
struct Sqrt2 {
    T a, b, c;     // inputs
    T sum, k;      // a + c, clamped
    T a1, b1, c1;  // scaled
    T d, dc, s;    // det', clamped, sqrt
    T den0, den, sq, kr, scale;
    T out[3];

    void run(T a_, T b_, T c_) {
        a = a_;
        b = b_;
        c = c_;
        const T tiny = static_cast<T>(1e-20);
        sum = a + c;
        k = std::max(sum, tiny);
        a1 = a / k;
        b1 = b / k;
        c1 = c / k;
        d = a1 * c1 - b1 * b1;
        dc = std::max(d, tiny);
        s = std::sqrt(dc);
        den0 = a1 + c1 + T(2) * s;
        den = std::max(den0, tiny);
        sq = std::sqrt(den);
        kr = std::sqrt(k);
        scale = kr / sq;
        out[0] = (a1 + s) * scale;
        out[1] = b1 * scale;
        out[2] = (c1 + s) * scale;
    }

    // Gradients of (a, b, c) from those of out.
    void backward(const T* g, T* g_in) const {
        const T tiny = static_cast<T>(1e-20);
        const T g_scale = g[0] * (a1 + s) + g[1] * b1 + g[2] * (c1 + s);
        T g_a1 = g[0] * scale, g_b1 = g[1] * scale, g_c1 = g[2] * scale;
        T g_s = (g[0] + g[2]) * scale;
        const T g_kr = g_scale / sq;
        const T g_sq = -g_scale * kr / (sq * sq);
        T g_k = g_kr / (T(2) * kr);
        const T g_den = g_sq / (T(2) * sq);
        if (den0 >= tiny) {
            g_a1 += g_den;
            g_c1 += g_den;
            g_s += T(2) * g_den;
        }
        const T g_dc = g_s / (T(2) * s);
        if (d >= tiny) {
            g_a1 += g_dc * c1;
            g_c1 += g_dc * a1;
            g_b1 -= T(2) * b1 * g_dc;
        }
        T g_a = g_a1 / k, g_b = g_b1 / k, g_c = g_c1 / k;
        g_k -= (g_a1 * a + g_b1 * b + g_c1 * c) / (k * k);
        if (sum >= tiny) {
            g_a += g_k;
            g_c += g_k;
        }
        g_in[0] = g_a;
        g_in[1] = g_b;
        g_in[2] = g_c;
    }
};

template <typename T>
void forward_range(int64_t first, int64_t last, const T* ma, const T* cov_a, const T* conic_a, const T* depth_a,
                   const T* mb, const T* cov_b, const T* depth_b, const Limits& lim, T* out) {
    Sqrt2<T> sb, ia;
    for (int64_t i = first; i < last; ++i) {
        T* o = out + 7 * i;
        if (!row_valid(i, ma, cov_a, conic_a, depth_a, mb, cov_b, depth_b, lim)) {
            o[0] = 1;
            o[1] = o[2] = 0;
            o[3] = 1;
            o[4] = o[5] = o[6] = 0;
            continue;
        }
        const T* s_b = cov_b + 4 * i;
        const T* q_a = conic_a + 3 * i;
        sb.run(s_b[0], s_b[1], s_b[3]);
        ia.run(q_a[0], q_a[1], q_a[2]);
        const T a00 = sb.out[0] * ia.out[0] + sb.out[1] * ia.out[1];
        const T a01 = sb.out[0] * ia.out[1] + sb.out[1] * ia.out[2];
        const T a10 = sb.out[1] * ia.out[0] + sb.out[2] * ia.out[1];
        const T a11 = sb.out[1] * ia.out[1] + sb.out[2] * ia.out[2];
        const T* m_a = ma + 2 * i;
        const T* m_b = mb + 2 * i;
        o[0] = a00;
        o[1] = a01;
        o[2] = a10;
        o[3] = a11;
        o[4] = m_b[0] - (a00 * m_a[0] + a01 * m_a[1]);
        o[5] = m_b[1] - (a10 * m_a[0] + a11 * m_a[1]);
        o[6] = 1;
    }
}

template <typename T>
void backward_range(int64_t first, int64_t last, const T* ma, const T* cov_a, const T* conic_a, const T* depth_a,
                    const T* mb, const T* cov_b, const T* depth_b, const Limits& lim, const T* grad_out, T* g_ma,
                    T* g_conic_a, T* g_mb, T* g_cov_b) {
    Sqrt2<T> sb, ia;
    for (int64_t i = first; i < last; ++i) {
        T* gma = g_ma + 2 * i;
        T* gqa = g_conic_a + 3 * i;
        T* gmb = g_mb + 2 * i;
        T* gsb = g_cov_b + 4 * i;
        gma[0] = gma[1] = gmb[0] = gmb[1] = 0;
        gqa[0] = gqa[1] = gqa[2] = 0;
        gsb[0] = gsb[1] = gsb[2] = gsb[3] = 0;
        if (!row_valid(i, ma, cov_a, conic_a, depth_a, mb, cov_b, depth_b, lim)) continue;
        const T* s_b = cov_b + 4 * i;
        const T* q_a = conic_a + 3 * i;
        sb.run(s_b[0], s_b[1], s_b[3]);
        ia.run(q_a[0], q_a[1], q_a[2]);
        const T* R = sb.out;  // sqrt(S_b) (a, b, c)
        const T* I = ia.out;  // sqrt(S_a^-1)
        const T a00 = R[0] * I[0] + R[1] * I[1];
        const T a01 = R[0] * I[1] + R[1] * I[2];
        const T a10 = R[1] * I[0] + R[2] * I[1];
        const T a11 = R[1] * I[1] + R[2] * I[2];
        const T* m_a = ma + 2 * i;
        const T* g = grad_out + 7 * i;
        const T g_cx = g[4], g_cy = g[5];
        gmb[0] = g_cx;
        gmb[1] = g_cy;
        gma[0] = -(g_cx * a00 + g_cy * a10);
        gma[1] = -(g_cx * a01 + g_cy * a11);
        const T g00 = g[0] - g_cx * m_a[0], g01 = g[1] - g_cx * m_a[1];
        const T g10 = g[2] - g_cy * m_a[0], g11 = g[3] - g_cy * m_a[1];
        const T g_R[3] = {g00 * I[0] + g01 * I[1],
                          g00 * I[1] + g01 * I[2] + g10 * I[0] + g11 * I[1],
                          g10 * I[1] + g11 * I[2]};
        const T g_I[3] = {g00 * R[0] + g10 * R[1],
                          g00 * R[1] + g01 * R[0] + g10 * R[2] + g11 * R[1],
                          g01 * R[1] + g11 * R[2]};
        T g_sb[3], g_ia[3];
        sb.backward(g_R, g_sb);
        ia.backward(g_I, g_ia);
        gsb[0] = g_sb[0];
        gsb[1] = g_sb[1];
        gsb[3] = g_sb[2];
        gqa[0] = g_ia[0];
        gqa[1] = g_ia[1];
        gqa[2] = g_ia[2];
    }
}

int parallel_blocks(int64_t n, int64_t threads, const std::function<void(int64_t, int64_t)>& fn) {
    try {
        const int64_t blocks = (n + kBlockRows - 1) / kBlockRows;
        threads = std::max<int64_t>(1, std::min<int64_t>(threads, blocks));
        if (threads <= 1) {
            fn(0, n);
            return kOk;
        }
        std::vector<std::exception_ptr> errors(static_cast<size_t>(threads));
        auto worker = [&](int64_t w) {
            try {
                for (int64_t b = w; b < blocks; b += threads) fn(b * kBlockRows, std::min(n, (b + 1) * kBlockRows));
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

}  // namespace

#define FF_DEFINE(SUFFIX, SCALAR)                                                                                   \
    extern "C" int ff_forward_##SUFFIX(const SCALAR* ma, const SCALAR* cov_a, const SCALAR* conic_a,               \
                                       const SCALAR* depth_a, const SCALAR* mb, const SCALAR* cov_b,               \
                                       const SCALAR* depth_b, int64_t n, double near_plane, double max_trace,      \
                                       double max_screen, int64_t threads, SCALAR* out) {                          \
        const Limits lim{near_plane, max_trace, max_screen};                                                        \
        return parallel_blocks(n, threads, [&](int64_t first, int64_t last) {                                       \
            forward_range<SCALAR>(first, last, ma, cov_a, conic_a, depth_a, mb, cov_b, depth_b, lim, out);          \
        });                                                                                                         \
    }                                                                                                               \
    extern "C" int ff_backward_##SUFFIX(const SCALAR* ma, const SCALAR* cov_a, const SCALAR* conic_a,              \
                                        const SCALAR* depth_a, const SCALAR* mb, const SCALAR* cov_b,              \
                                        const SCALAR* depth_b, int64_t n, double near_plane, double max_trace,     \
                                        double max_screen, int64_t threads, const SCALAR* grad_out, SCALAR* g_ma,  \
                                        SCALAR* g_conic_a, SCALAR* g_mb, SCALAR* g_cov_b) {                        \
        const Limits lim{near_plane, max_trace, max_screen};                                                        \
        return parallel_blocks(n, threads, [&](int64_t first, int64_t last) {                                       \
            backward_range<SCALAR>(first, last, ma, cov_a, conic_a, depth_a, mb, cov_b, depth_b, lim, grad_out,     \
                                   g_ma, g_conic_a, g_mb, g_cov_b);                                                 \
        });                                                                                                         \
    }

FF_DEFINE(f32, float)
FF_DEFINE(f64, double)

extern "C" int ff_abi_version() { return kAbiVersion; }
