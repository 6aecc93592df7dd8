// 4DGS's HexPlane regularisers on the CPU: the total and its gradient in one pass over the planes.
//
// Compiled on first use by baselines/fourdgs/regularization_kernel.py into a plain shared library
// (no Python or torch headers) and called through ctypes. It computes what
// regularization._WeightedPlaneRegularisation computes (the torch Function, the oracle of the
// tests), for planes p of shape [B, C, H, W] with weights smooth[p] and l1[p]:
//     total = sum_p smooth[p] / M_p * sum s_p^2 + l1[p] / numel_p * sum |p - 1|,
//     s_p[h] = p[h + 2] + p[h] - 2 p[h + 1] along H (dimension -2), M_p = B C (H - 2) W,
// and, in the same pass, d total / d p:
//     grad[h] = 2 smooth / M (s[h - 2] + s[h] - 2 s[h - 1]) + l1 / numel sign(p[h] - 1)
// (s[k] = 0 outside 0 <= k <= H - 3; sign 0 at p = 1, as autograd's abs). The smoothness term is
// quadratic, so its gradient is the linear map D^T D of the plane: the backward of the autograd
// Function only scales these gradients by the incoming gradient.
//
// Layout: each plane comes with its own pointer and element strides, so views into one shared
// channels-last table (strides (.., 1, W C, C)) and contiguous planes run alike; the gradient has
// the plane's strides. One row h of a plane (all b, c, w) is walked as up to three nested runs,
// the dimensions sorted by stride and merged where dense (a channels-last row is one run of W C
// contiguous values).
//
// Work split: every plane's rows are cut into blocks of about kBlockValues values (a fixed size,
// independent of the thread count); a block recomputes the two rows of s before its first row,
// streams its rows once (reading rows h, h + 1, h + 2, the last two still in cache from the row
// before) and writes each gradient row once. Sums run in double, per block in a fixed order, and
// the blocks' sums are added in block order: 1, 2 or 16 threads give bitwise identical results.
// Threads: std::thread per call, as the other kernels (torch's OpenMP pool is not touched).

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <functional>
#include <mutex>
#include <new>
#include <system_error>
#include <thread>
#include <vector>

namespace {

constexpr int kAbiVersion = 1;
constexpr int kOk = 0;
constexpr int kOutOfMemory = 2;
constexpr int kFailed = 3;
// Values per work item: large enough that the two recomputed rows of s are a few percent of it.
constexpr int64_t kBlockValues = 1 << 16;

// One plane: data and gradient (nullptr: no gradient wanted) with the plane's element strides.
template <typename scalar_t>
struct Plane {
    const scalar_t* data;
    scalar_t* grad;
    int64_t size[4];    // B, C, H, W
    int64_t stride[4];  // in elements
    double smooth, l1;  // the weights (0: term off)
    bool has_smooth() const { return smooth != 0.0 && size[2] >= 3; }
    int64_t numel() const { return size[0] * size[1] * size[2] * size[3]; }
    int64_t row_values() const { return size[0] * size[1] * size[3]; }
};

// The values of one row as up to three nested runs (count, stride), innermost first.
struct RowRuns {
    int64_t count[3] = {1, 1, 1};
    int64_t stride[3] = {0, 0, 0};
    int dims = 0;

    template <typename scalar_t>
    explicit RowRuns(const Plane<scalar_t>& p) {
        // (count, stride) of B, C, W, sizes of 1 dropped, sorted by stride, dense neighbours merged
        int64_t c[3], s[3];
        int n = 0;
        for (int d : {0, 1, 3}) {
            if (p.size[d] == 1) continue;
            c[n] = p.size[d];
            s[n] = p.stride[d];
            ++n;
        }
        for (int i = 1; i < n; ++i)
            for (int j = i; j > 0 && s[j] < s[j - 1]; --j) {
                std::swap(s[j], s[j - 1]);
                std::swap(c[j], c[j - 1]);
            }
        for (int i = 0; i < n; ++i) {
            if (dims > 0 && s[i] == count[dims - 1] * stride[dims - 1]) {
                count[dims - 1] *= c[i];
            } else {
                count[dims] = c[i];
                stride[dims] = s[i];
                ++dims;
            }
        }
        if (dims == 0) {  // a single value per row
            dims = 1;
            stride[0] = 1;
        }
    }

    // Calls fn(offset, first, n, step) for every run of the row: n values at offset + i * step,
    // numbered first + i in the row's dense order (the index into the row buffers).
    template <typename Fn>
    void for_runs(Fn&& fn) const {
        int64_t first = 0;
        for (int64_t k = 0; k < count[2]; ++k)
            for (int64_t j = 0; j < count[1]; ++j) {
                fn(k * stride[2] + j * stride[1], first, count[0], stride[0]);
                first += count[0];
            }
    }
};

// Sum of values[i] (and of their squares) in double, four running sums added in a fixed order.
template <typename scalar_t>
inline double sum_squares(const scalar_t* values, int64_t n) {
    double acc[4] = {0, 0, 0, 0};
    int64_t i = 0;
    for (; i + 4 <= n; i += 4)
        for (int l = 0; l < 4; ++l) acc[l] += static_cast<double>(values[i + l]) * static_cast<double>(values[i + l]);
    for (; i < n; ++i) acc[0] += static_cast<double>(values[i]) * static_cast<double>(values[i]);
    return (acc[0] + acc[1]) + (acc[2] + acc[3]);
}

template <typename scalar_t>
inline double sum_values(const scalar_t* values, int64_t n) {
    double acc[4] = {0, 0, 0, 0};
    int64_t i = 0;
    for (; i + 4 <= n; i += 4)
        for (int l = 0; l < 4; ++l) acc[l] += static_cast<double>(values[i + l]);
    for (; i < n; ++i) acc[0] += static_cast<double>(values[i]);
    return (acc[0] + acc[1]) + (acc[2] + acc[3]);
}

// s[first + i] = (p[h + 2] + p[h]) - 2 p[h + 1] on one run (torch.sub(a + b, c, alpha=2)'s order).
template <typename scalar_t>
inline void second_difference(const scalar_t* row, int64_t row_stride, int64_t n, int64_t step, scalar_t* s) {
    const scalar_t* r1 = row + row_stride;
    const scalar_t* r2 = row + 2 * row_stride;
    if (step == 1) {
        for (int64_t i = 0; i < n; ++i) s[i] = (r2[i] + row[i]) - scalar_t(2) * r1[i];
    } else {
        for (int64_t i = 0; i < n; ++i) s[i] = (r2[i * step] + row[i * step]) - scalar_t(2) * r1[i * step];
    }
}

// One gradient run: g = (k s[h - 2] + k s[h]) - 2 (k s[h - 1]) + l1k sign(p - 1), and |p - 1|
// into `absolute` (when the L1 term is on). kSmooth / kL1: which terms the plane has.
template <typename scalar_t, bool kSmooth, bool kL1>
inline void gradient_run(const scalar_t* p, scalar_t* g, int64_t n, int64_t step, const scalar_t* s_prev2,
                         const scalar_t* s_prev1, const scalar_t* s_here, scalar_t k, scalar_t l1k,
                         scalar_t* absolute) {
    for (int64_t i = 0; i < n; ++i) {
        scalar_t value = scalar_t(0);
        if (kSmooth) value = (k * s_prev2[i] + k * s_here[i]) - scalar_t(2) * (k * s_prev1[i]);
        if (kL1) {
            const scalar_t d = p[i * step] - scalar_t(1);
            const scalar_t sign = static_cast<scalar_t>((d > scalar_t(0)) - (d < scalar_t(0)));
            value += l1k * sign;
            absolute[i] = std::fabs(d);
        }
        if (g != nullptr) g[i * step] = value;
    }
}

// |p - 1| of one run (no gradient wanted).
template <typename scalar_t>
inline void absolute_run(const scalar_t* p, int64_t n, int64_t step, scalar_t* absolute) {
    for (int64_t i = 0; i < n; ++i) absolute[i] = std::fabs(p[i * step] - scalar_t(1));
}

struct Item {
    int64_t plane, first_row, last_row;
};

// Sums of one block of rows: sum s^2 over its rows of s, sum |p - 1| over its rows.
struct BlockSums {
    double squares = 0, absolute = 0;
};

template <typename scalar_t>
BlockSums run_block(const Plane<scalar_t>& P, const RowRuns& runs, int64_t h0, int64_t h1) {
    const int64_t R = P.row_values(), H = P.size[2], row_stride = P.stride[2];
    const bool smooth = P.has_smooth(), l1 = P.l1 != 0.0, grad = P.grad != nullptr;
    const scalar_t k = static_cast<scalar_t>(2.0 * P.smooth / static_cast<double>(P.size[0] * P.size[1] * (H - 2) * P.size[3]));
    const scalar_t l1k = static_cast<scalar_t>(P.l1 / static_cast<double>(P.numel()));
    // ring of s rows h - 2, h - 1, h (zeros where s is not defined), and a row of |p - 1|
    std::vector<scalar_t> ring(smooth ? static_cast<size_t>(3 * R) : 0, scalar_t(0));
    std::vector<scalar_t> absolute(l1 ? static_cast<size_t>(R) : 0);
    auto slot = [&](int64_t h) { return ring.data() + ((h % 3 + 3) % 3) * R; };
    auto fill_s = [&](int64_t h) {  // row h of s into its slot (zeros outside 0..H-3)
        scalar_t* s = slot(h);
        if (h < 0 || h > H - 3) {
            std::fill(s, s + R, scalar_t(0));
            return;
        }
        runs.for_runs([&](int64_t offset, int64_t first, int64_t n, int64_t step) {
            second_difference(P.data + h * row_stride + offset, row_stride, n, step, s + first);
        });
    };
    BlockSums sums;
    if (smooth) {
        fill_s(h0 - 2);
        fill_s(h0 - 1);
    }
    for (int64_t h = h0; h < h1; ++h) {
        if (smooth) {
            fill_s(h);
            if (h <= H - 3) sums.squares += sum_squares(slot(h), R);
        }
        if (!grad && !l1) continue;
        const scalar_t* prev2 = smooth ? slot(h - 2) : nullptr;
        const scalar_t* prev1 = smooth ? slot(h - 1) : nullptr;
        const scalar_t* here = smooth ? slot(h) : nullptr;
        runs.for_runs([&](int64_t offset, int64_t first, int64_t n, int64_t step) {
            const scalar_t* p = P.data + h * row_stride + offset;
            scalar_t* g = grad ? P.grad + h * row_stride + offset : nullptr;
            scalar_t* a = l1 ? absolute.data() + first : nullptr;
            if (!grad) {
                absolute_run(p, n, step, a);
            } else if (smooth && l1) {
                gradient_run<scalar_t, true, true>(p, g, n, step, prev2 + first, prev1 + first, here + first, k, l1k, a);
            } else if (smooth) {
                gradient_run<scalar_t, true, false>(p, g, n, step, prev2 + first, prev1 + first, here + first, k, l1k, a);
            } else {
                gradient_run<scalar_t, false, true>(p, g, n, step, nullptr, nullptr, nullptr, k, l1k, a);
            }
        });
        if (l1) sums.absolute += sum_values(absolute.data(), R);
    }
    return sums;
}

// Runs fn(item) for item in [0, n) on up to `threads` workers (dynamic schedule). An exception in
// a worker stops the others and is rethrown after all have joined.
void parallel_items(int64_t n, int64_t threads, const std::function<void(int64_t)>& fn) {
    threads = std::max<int64_t>(1, std::min<int64_t>(threads, n));
    if (threads == 1) {
        for (int64_t i = 0; i < n; ++i) fn(i);
        return;
    }
    std::atomic<int64_t> next{0};
    std::mutex error_mutex;
    std::exception_ptr error;
    auto worker = [&]() {
        try {
            for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i);
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
            pool.emplace_back(worker);
        } catch (const std::system_error&) {
            break;  // the workers already running finish the items
        }
    }
    worker();
    for (auto& t : pool) t.join();
    if (error) std::rethrow_exception(error);
}

template <typename scalar_t>
double regularise(const std::vector<Plane<scalar_t>>& planes, int64_t threads) {
    std::vector<Item> items;
    std::vector<RowRuns> runs;
    for (int64_t p = 0; p < static_cast<int64_t>(planes.size()); ++p) {
        const Plane<scalar_t>& P = planes[p];
        runs.emplace_back(P);
        if (!P.has_smooth() && P.l1 == 0.0) continue;  // no term: no work, no gradient
        const int64_t rows_per_item = std::max<int64_t>(1, kBlockValues / std::max<int64_t>(1, P.row_values()));
        for (int64_t h = 0; h < P.size[2]; h += rows_per_item)
            items.push_back({p, h, std::min(P.size[2], h + rows_per_item)});
    }
    std::vector<BlockSums> sums(items.size());
    parallel_items(static_cast<int64_t>(items.size()), threads, [&](int64_t i) {
        const Item& item = items[i];
        sums[i] = run_block(planes[item.plane], runs[item.plane], item.first_row, item.last_row);
    });
    // per plane in block order, then the planes in order
    double total = 0;
    size_t i = 0;
    for (int64_t p = 0; p < static_cast<int64_t>(planes.size()); ++p) {
        BlockSums plane_sums;
        for (; i < items.size() && items[i].plane == p; ++i) {
            plane_sums.squares += sums[i].squares;
            plane_sums.absolute += sums[i].absolute;
        }
        const Plane<scalar_t>& P = planes[p];
        if (P.has_smooth())
            total += P.smooth * plane_sums.squares /
                     static_cast<double>(P.size[0] * P.size[1] * (P.size[2] - 2) * P.size[3]);
        if (P.l1 != 0.0) total += P.l1 * plane_sums.absolute / static_cast<double>(P.numel());
    }
    return total;
}

template <typename F>
int guarded(F&& fn) {
    try {
        fn();
        return kOk;
    } catch (const std::bad_alloc&) {
        return kOutOfMemory;
    } catch (...) {
        return kFailed;
    }
}

}  // namespace

// Entry points. Per plane p < count: data[p] and grad[p] are addresses (grad 0: no gradient
// wanted; a plane without a term gets none written either), sizes[4 p .. 4 p + 3] = B, C, H, W,
// strides[4 p ..] the element strides of the plane and of its gradient, smooth[p] and l1[p] the
// weights. *total receives the regularisers' sum.
#define RK_ENTRY_POINT(SUFFIX, SCALAR)                                                                        \
    extern "C" int rk_forward_##SUFFIX(int64_t count, const int64_t* data, const int64_t* grad,              \
                                       const int64_t* sizes, const int64_t* strides, const double* smooth,     \
                                       const double* l1, int64_t threads, double* total) {                    \
        return guarded([&] {                                                                                  \
            std::vector<Plane<SCALAR>> planes(static_cast<size_t>(count));                                    \
            for (int64_t p = 0; p < count; ++p) {                                                             \
                Plane<SCALAR>& P = planes[p];                                                                 \
                P.data = reinterpret_cast<const SCALAR*>(static_cast<uintptr_t>(data[p]));                    \
                P.grad = reinterpret_cast<SCALAR*>(static_cast<uintptr_t>(grad[p]));                          \
                for (int d = 0; d < 4; ++d) {                                                                 \
                    P.size[d] = sizes[4 * p + d];                                                             \
                    P.stride[d] = strides[4 * p + d];                                                         \
                }                                                                                             \
                P.smooth = smooth[p];                                                                         \
                P.l1 = l1[p];                                                                                 \
            }                                                                                                 \
            *total = regularise(planes, threads);                                                             \
        });                                                                                                   \
    }

RK_ENTRY_POINT(f32, float)
RK_ENTRY_POINT(f64, double)

extern "C" int rk_abi_version() { return kAbiVersion; }
