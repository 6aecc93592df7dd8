// EWA projection of 3D Gaussians into one pinhole camera on the CPU: forward and hand-written backward.
//
// Compiled on first use by baselines/render/project_kernel.py into a plain shared library (no
// Python or torch headers) and called through ctypes with raw pointers to contiguous tensors.
// It computes what project_gaussians_torch (baselines/render/projection.py) computes, which stays
// the oracle of the tests and the fallback; the same rules in the same order of operations:
//     p = R mu + t; outside [near, far] the camera point is replaced by (0, 0, 1) (no gradient);
//     J's tx/z, ty/z clamped to the FOV margin; T = J R Rq diag(s) (rows t0, t1);
//     cov2d = T T^T + eps2d I; det = |t0 x t1|^2 + eps2d (a0 + c0) + eps2d^2;
//     ok = in range, finite, det > 0; not ok: cov2d = I, conic = I (constants, no gradient);
//     conic = (c, -b, a) / det; means2d = (fx x / z + cx, fy y / z + cy); depth = z (raw);
//     radii / visible as gsplat (opacity-aware extent), no gradient.
// Backward: gradients of means [N, 3], quats [N, 4] and scales [N, 3] from those of means2d,
// cov2d, conics and depths; the camera is a constant. Ties of the FOV clamp split the gradient
// in halves, as torch's minimum / maximum do.
//
// Work split: every Gaussian is independent (forward and backward write only its own rows), so
// points are split into blocks over std::threads; results do not depend on the thread count.

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
constexpr int64_t kBlockPoints = 4096;  // Gaussians per work item
constexpr double kAlphaThreshold = 1.0 / 255.0;
constexpr double kExtendMax = 3.33;
constexpr double kRadiusCap = 16777216.0;  // 2^24
constexpr double kFovClampMargin = 0.3;

template <typename T>
struct Camera {
    T R[9];
    T t[3];
    T fx, fy, cx, cy;
    T lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
    T width, height, near_plane, far_plane, eps2d;

    Camera(const T* viewmat, const T* K, int64_t w, int64_t h, double near_, double far_, double eps) {
        for (int r = 0; r < 3; ++r) {
            for (int c = 0; c < 3; ++c) R[3 * r + c] = viewmat[4 * r + c];
            t[r] = viewmat[4 * r + 3];
        }
        fx = K[0];
        fy = K[4];
        cx = K[2];
        cy = K[5];
        width = static_cast<T>(w);
        height = static_cast<T>(h);
        // as the torch twin: 0.5 * width / fx etc. in the tensors' dtype
        const T tan_fovx = static_cast<T>(0.5) * width / fx;
        const T tan_fovy = static_cast<T>(0.5) * height / fy;
        const T margin = static_cast<T>(kFovClampMargin);
        lim_x_pos = (width - cx) / fx + margin * tan_fovx;
        lim_x_neg = cx / fx + margin * tan_fovx;
        lim_y_pos = (height - cy) / fy + margin * tan_fovy;
        lim_y_neg = cy / fy + margin * tan_fovy;
        near_plane = static_cast<T>(near_);
        far_plane = static_cast<T>(far_);
        eps2d = static_cast<T>(eps);
    }
};

// Rotation matrix of a quaternion (w, x, y, z), normalised; a (near-)zero quaternion gives identity.
// Returns whether the quaternion was usable (else its gradient is zero) and its norm.
template <typename T>
bool quat_rotmat(const T* q, T* qn, T& norm, T* Rq) {
    norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const bool usable = norm > static_cast<T>(1e-12);
    if (usable) {
        for (int k = 0; k < 4; ++k) qn[k] = q[k] / norm;
    } else {
        qn[0] = 1;
        qn[1] = qn[2] = qn[3] = 0;
    }
    const T w = qn[0], x = qn[1], y = qn[2], z = qn[3];
    Rq[0] = 1 - 2 * (y * y + z * z);
    Rq[1] = 2 * (x * y - w * z);
    Rq[2] = 2 * (x * z + w * y);
    Rq[3] = 2 * (x * y + w * z);
    Rq[4] = 1 - 2 * (x * x + z * z);
    Rq[5] = 2 * (y * z - w * x);
    Rq[6] = 2 * (x * z - w * y);
    Rq[7] = 2 * (y * z + w * x);
    Rq[8] = 1 - 2 * (x * x + y * y);
    return usable;
}

// Everything the forward computes for one Gaussian and the backward needs again.
template <typename T>
struct Point {
    T x, y, z;        // camera-space mean (raw)
    bool in_range;
    T xs, ys, zs;     // safe stand-ins
    T u, v;           // xs / zs, ys / zs (before the clamp)
    T uc, vc;         // clamped
    T tx, ty;
    T jx, jxz, jy, jyz;
    T row0[3], row1[3];
    T qn[4], qnorm;
    bool q_usable;
    T Rq[9];
    T M[9];           // Rq diag(s)
    T t0[3], t1[3];
    T k[3];           // t0 x t1
    T a0, c0, a, b, c, det;
    bool ok;
};

template <typename T>
inline bool finite(T value) {
    return std::isfinite(value);
}

template <typename T>
void compute_point(const Camera<T>& cam, const T* mean, const T* quat, const T* scale, Point<T>& P) {
    const T* R = cam.R;
    // means @ R.T + t: the matmul's sum in index order, then + t
    P.x = (mean[0] * R[0] + mean[1] * R[1] + mean[2] * R[2]) + cam.t[0];
    P.y = (mean[0] * R[3] + mean[1] * R[4] + mean[2] * R[5]) + cam.t[1];
    P.z = (mean[0] * R[6] + mean[1] * R[7] + mean[2] * R[8]) + cam.t[2];
    P.in_range = P.z >= cam.near_plane && P.z <= cam.far_plane;
    P.zs = P.in_range ? P.z : T(1);
    P.xs = P.in_range ? P.x : T(0);
    P.ys = P.in_range ? P.y : T(0);
    P.u = P.xs / P.zs;
    P.v = P.ys / P.zs;
    P.uc = std::min(cam.lim_x_pos, std::max(-cam.lim_x_neg, P.u));
    P.vc = std::min(cam.lim_y_pos, std::max(-cam.lim_y_neg, P.v));
    P.tx = P.zs * P.uc;
    P.ty = P.zs * P.vc;
    const T z2 = P.zs * P.zs;
    P.jx = cam.fx / P.zs;
    P.jxz = -cam.fx * P.tx / z2;
    P.jy = cam.fy / P.zs;
    P.jyz = -cam.fy * P.ty / z2;
    for (int r = 0; r < 3; ++r) {
        P.row0[r] = P.jx * R[r] + P.jxz * R[6 + r];
        P.row1[r] = P.jy * R[3 + r] + P.jyz * R[6 + r];
    }
    P.q_usable = quat_rotmat(quat, P.qn, P.qnorm, P.Rq);
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) P.M[3 * r + c] = P.Rq[3 * r + c] * scale[c];
    for (int c = 0; c < 3; ++c) {
        P.t0[c] = P.row0[0] * P.M[c] + P.row0[1] * P.M[3 + c] + P.row0[2] * P.M[6 + c];
        P.t1[c] = P.row1[0] * P.M[c] + P.row1[1] * P.M[3 + c] + P.row1[2] * P.M[6 + c];
    }
    P.a0 = P.t0[0] * P.t0[0] + P.t0[1] * P.t0[1] + P.t0[2] * P.t0[2];
    P.c0 = P.t1[0] * P.t1[0] + P.t1[1] * P.t1[1] + P.t1[2] * P.t1[2];
    P.a = P.a0 + cam.eps2d;
    P.b = P.t0[0] * P.t1[0] + P.t0[1] * P.t1[1] + P.t0[2] * P.t1[2];
    P.c = P.c0 + cam.eps2d;
    P.k[0] = P.t0[1] * P.t1[2] - P.t0[2] * P.t1[1];
    P.k[1] = P.t0[2] * P.t1[0] - P.t0[0] * P.t1[2];
    P.k[2] = P.t0[0] * P.t1[1] - P.t0[1] * P.t1[0];
    P.det = (P.k[0] * P.k[0] + P.k[1] * P.k[1] + P.k[2] * P.k[2]) + cam.eps2d * (P.a0 + P.c0) + cam.eps2d * cam.eps2d;
    const bool fin = finite(P.a) && finite(P.b) && finite(P.c) && finite(P.x) && finite(P.y) && finite(P.z);
    P.ok = P.in_range && fin && P.det > 0;
}

template <typename T>
void forward_range(const Camera<T>& cam, const T* means, const T* quats, const T* scales, const T* opacities,
                   int64_t first, int64_t last, T* means2d, T* cov2d, T* conics, T* depths, int32_t* radii,
                   uint8_t* visible) {
    Point<T> P;
    const T thr = static_cast<T>(kAlphaThreshold);
    for (int64_t i = first; i < last; ++i) {
        compute_point(cam, means + 3 * i, quats + 4 * i, scales + 3 * i, P);
        const T det_s = P.ok ? P.det : T(1);
        const T a_s = P.ok ? P.a : T(1);
        const T b_s = P.ok ? P.b : T(0);
        const T c_s = P.ok ? P.c : T(1);
        conics[3 * i] = c_s / det_s;
        conics[3 * i + 1] = -b_s / det_s;
        conics[3 * i + 2] = a_s / det_s;
        cov2d[4 * i] = a_s;
        cov2d[4 * i + 1] = b_s;
        cov2d[4 * i + 2] = b_s;
        cov2d[4 * i + 3] = c_s;
        const T mx = cam.fx * P.xs / P.zs + cam.cx;
        const T my = cam.fy * P.ys / P.zs + cam.cy;
        means2d[2 * i] = mx;
        means2d[2 * i + 1] = my;
        depths[i] = P.z;
        // radii and visibility (no gradient)
        bool ok = P.ok;
        T extend = static_cast<T>(kExtendMax);
        if (opacities != nullptr) {
            const T o = opacities[i];
            ok = ok && o >= thr;
            const T ratio = std::max(o / thr, T(1));
            extend = std::min(extend, std::sqrt(T(2) * std::log(ratio)));
        }
        const T cap = static_cast<T>(kRadiusCap);
        const T rx = std::min(std::ceil(extend * std::sqrt(std::max(a_s, T(0)))), cap);
        const T ry = std::min(std::ceil(extend * std::sqrt(std::max(c_s, T(0)))), cap);
        const bool on_screen = (mx + rx > 0) && (mx - rx < cam.width) && (my + ry > 0) && (my - ry < cam.height);
        const bool vis = ok && on_screen && (rx > 0 || ry > 0) && finite(mx) && finite(my);
        visible[i] = vis ? 1 : 0;
        radii[2 * i] = vis ? static_cast<int32_t>(rx) : 0;
        radii[2 * i + 1] = vis ? static_cast<int32_t>(ry) : 0;
    }
}

// d min(hi, max(lo, u)) / du with torch's tie rule (a tie passes half the gradient).
template <typename T>
inline T clamp_slope(T u, T lo, T hi) {
    const T m = std::max(lo, u);
    const T inner = u > lo ? T(1) : (u == lo ? T(0.5) : T(0));
    const T outer = m < hi ? T(1) : (m == hi ? T(0.5) : T(0));
    return inner * outer;
}

template <typename T>
void backward_range(const Camera<T>& cam, const T* means, const T* quats, const T* scales, int64_t first,
                    int64_t last, const T* g_means2d, const T* g_cov2d, const T* g_conics, const T* g_depths,
                    T* g_means, T* g_quats, T* g_scales) {
    Point<T> P;
    const T* R = cam.R;
    for (int64_t i = first; i < last; ++i) {
        const T* scale = scales + 3 * i;
        compute_point(cam, means + 3 * i, quats + 4 * i, scale, P);
        T g_xs = 0, g_ys = 0, g_zs = 0;
        T g_q[4] = {0, 0, 0, 0};
        T g_s[3] = {0, 0, 0};
        // means2d = (fx xs / zs + cx, fy ys / zs + cy)
        const T gmx = g_means2d ? g_means2d[2 * i] : T(0);
        const T gmy = g_means2d ? g_means2d[2 * i + 1] : T(0);
        g_xs += cam.fx * gmx / P.zs;
        g_ys += cam.fy * gmy / P.zs;
        g_zs -= (cam.fx * P.xs * gmx + cam.fy * P.ys * gmy) / (P.zs * P.zs);
        if (P.ok && (g_cov2d || g_conics)) {
            T ga = 0, gb = 0, gc = 0, gdet = 0;
            if (g_cov2d) {
                const T* g = g_cov2d + 4 * i;
                ga += g[0];
                gb += g[1] + g[2];
                gc += g[3];
            }
            if (g_conics) {
                const T* g = g_conics + 3 * i;
                const T inv = T(1) / P.det;
                gc += g[0] * inv;
                gb -= g[1] * inv;
                ga += g[2] * inv;
                gdet -= (g[0] * P.c - g[1] * P.b + g[2] * P.a) * inv * inv;
            }
            const T ga0 = ga + cam.eps2d * gdet;
            const T gc0 = gc + cam.eps2d * gdet;
            // d|t0 x t1|^2 / dt0 = t1 x gk, / dt1 = gk x t0 with gk = 2 gdet k. gk first, as torch's
            // chain does: for a blown-up Gaussian (|t| ~ 1e13) t1 x k overflows float32 while gdet
            // is 0 (det = inf), and 0 * inf would be NaN where torch gives 0.
            const T* t0 = P.t0;
            const T* t1 = P.t1;
            const T gk[3] = {2 * gdet * P.k[0], 2 * gdet * P.k[1], 2 * gdet * P.k[2]};
            const T t1xgk[3] = {t1[1] * gk[2] - t1[2] * gk[1], t1[2] * gk[0] - t1[0] * gk[2], t1[0] * gk[1] - t1[1] * gk[0]};
            const T gkxt0[3] = {gk[1] * t0[2] - gk[2] * t0[1], gk[2] * t0[0] - gk[0] * t0[2], gk[0] * t0[1] - gk[1] * t0[0]};
            T g_t0[3], g_t1[3];
            for (int d = 0; d < 3; ++d) {
                g_t0[d] = 2 * ga0 * t0[d] + gb * t1[d] + t1xgk[d];
                g_t1[d] = 2 * gc0 * t1[d] + gb * t0[d] + gkxt0[d];
            }
            // t0[c] = sum_r row0[r] M[r][c]
            T g_row0[3], g_row1[3], g_Rq[9];
            for (int r = 0; r < 3; ++r) {
                g_row0[r] = g_t0[0] * P.M[3 * r] + g_t0[1] * P.M[3 * r + 1] + g_t0[2] * P.M[3 * r + 2];
                g_row1[r] = g_t1[0] * P.M[3 * r] + g_t1[1] * P.M[3 * r + 1] + g_t1[2] * P.M[3 * r + 2];
                for (int c = 0; c < 3; ++c) {
                    const T gM = P.row0[r] * g_t0[c] + P.row1[r] * g_t1[c];
                    g_s[c] += gM * P.Rq[3 * r + c];
                    g_Rq[3 * r + c] = gM * scale[c];
                }
            }
            // rotation matrix -> normalised quaternion -> quaternion
            if (P.q_usable) {
                const T w = P.qn[0], x = P.qn[1], y = P.qn[2], z = P.qn[3];
                const T* G = g_Rq;
                T gn[4];
                gn[0] = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
                gn[1] = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] - 2 * x * G[8]);
                gn[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] - 2 * y * G[8]);
                gn[3] = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] + y * G[7]);
                const T dot = gn[0] * w + gn[1] * x + gn[2] * y + gn[3] * z;
                for (int d = 0; d < 4; ++d) g_q[d] = (gn[d] - P.qn[d] * dot) / P.qnorm;
            }
            // row0 = jx R0 + jxz R2, row1 = jy R1 + jyz R2
            const T g_jx = g_row0[0] * R[0] + g_row0[1] * R[1] + g_row0[2] * R[2];
            const T g_jxz = g_row0[0] * R[6] + g_row0[1] * R[7] + g_row0[2] * R[8];
            const T g_jy = g_row1[0] * R[3] + g_row1[1] * R[4] + g_row1[2] * R[5];
            const T g_jyz = g_row1[0] * R[6] + g_row1[1] * R[7] + g_row1[2] * R[8];
            const T z2 = P.zs * P.zs;
            const T z3 = z2 * P.zs;
            g_zs -= (cam.fx * g_jx + cam.fy * g_jy) / z2;
            const T g_tx = -cam.fx * g_jxz / z2;
            const T g_ty = -cam.fy * g_jyz / z2;
            g_zs += 2 * (cam.fx * P.tx * g_jxz + cam.fy * P.ty * g_jyz) / z3;
            // tx = zs * clamp(xs / zs)
            g_zs += P.uc * g_tx + P.vc * g_ty;
            const T g_u = P.zs * g_tx * clamp_slope(P.u, -cam.lim_x_neg, cam.lim_x_pos);
            const T g_v = P.zs * g_ty * clamp_slope(P.v, -cam.lim_y_neg, cam.lim_y_pos);
            g_xs += g_u / P.zs;
            g_ys += g_v / P.zs;
            g_zs -= (P.u * g_u + P.v * g_v) / P.zs;
        }
        T g_p[3] = {P.in_range ? g_xs : T(0), P.in_range ? g_ys : T(0), P.in_range ? g_zs : T(0)};
        if (g_depths) g_p[2] += g_depths[i];
        // p = R mu + t
        for (int d = 0; d < 3; ++d) g_means[3 * i + d] = R[d] * g_p[0] + R[3 + d] * g_p[1] + R[6 + d] * g_p[2];
        for (int d = 0; d < 4; ++d) g_quats[4 * i + d] = g_q[d];
        for (int d = 0; d < 3; ++d) g_scales[3 * i + d] = g_s[d];
    }
}

// Runs fn(first, last) over blocks of [0, n) on up to `threads` workers; the first exception wins.
int parallel_blocks(int64_t n, int64_t threads, const std::function<void(int64_t, int64_t)>& fn) {
    try {
        const int64_t blocks = (n + kBlockPoints - 1) / kBlockPoints;
        threads = std::max<int64_t>(1, std::min<int64_t>(threads, blocks));
        if (threads <= 1) {
            fn(0, n);
            return kOk;
        }
        std::vector<std::exception_ptr> errors(static_cast<size_t>(threads));
        auto worker = [&](int64_t w) {
            try {
                for (int64_t b = w; b < blocks; b += threads)
                    fn(b * kBlockPoints, std::min(n, (b + 1) * kBlockPoints));
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

#define PJ_DEFINE(SUFFIX, SCALAR)                                                                                  \
    extern "C" int pj_forward_##SUFFIX(const SCALAR* means, const SCALAR* quats, const SCALAR* scales,             \
                                       const SCALAR* opacities, const SCALAR* viewmat, const SCALAR* K, int64_t n, \
                                       int64_t width, int64_t height, double near_plane, double far_plane,        \
                                       double eps2d, int64_t threads, SCALAR* means2d, SCALAR* cov2d,             \
                                       SCALAR* conics, SCALAR* depths, int32_t* radii, uint8_t* visible) {        \
        const Camera<SCALAR> cam(viewmat, K, width, height, near_plane, far_plane, eps2d);                         \
        return parallel_blocks(n, threads, [&](int64_t first, int64_t last) {                                      \
            forward_range<SCALAR>(cam, means, quats, scales, opacities, first, last, means2d, cov2d, conics,      \
                                  depths, radii, visible);                                                         \
        });                                                                                                        \
    }                                                                                                              \
    extern "C" int pj_backward_##SUFFIX(const SCALAR* means, const SCALAR* quats, const SCALAR* scales,            \
                                        const SCALAR* viewmat, const SCALAR* K, int64_t n, int64_t width,         \
                                        int64_t height, double near_plane, double far_plane, double eps2d,        \
                                        int64_t threads, const SCALAR* g_means2d, const SCALAR* g_cov2d,          \
                                        const SCALAR* g_conics, const SCALAR* g_depths, SCALAR* g_means,          \
                                        SCALAR* g_quats, SCALAR* g_scales) {                                       \
        const Camera<SCALAR> cam(viewmat, K, width, height, near_plane, far_plane, eps2d);                         \
        return parallel_blocks(n, threads, [&](int64_t first, int64_t last) {                                      \
            backward_range<SCALAR>(cam, means, quats, scales, first, last, g_means2d, g_cov2d, g_conics,          \
                                   g_depths, g_means, g_quats, g_scales);                                          \
        });                                                                                                        \
    }

PJ_DEFINE(f32, float)
PJ_DEFINE(f64, double)

extern "C" int pj_abi_version() { return kAbiVersion; }
